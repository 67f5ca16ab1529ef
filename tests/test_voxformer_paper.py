"""VoxFormer at ``size: paper``: ResNet-50 with torchvision's names, loaded from a file in torchvision's layout
(torchvision's original ImageNet release: no ``num_batches_tracked``; ``fc.*``, ``layer4.*`` beside); frozen batch
norms and first stage; query proposals read from a folder of VoxFormer's files; the network builds and trains. (Its
attention against naive references and a released checkpoint's parity: tests/test_voxformer_release.py.)"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from _camera_kitti import camera_kitti_copy
from distilkit.weights import PartialWeights, load_weights
from distilkit.errors import DataError
from distilkit_adapters.voxformer.deformable import plane_shape
from distilkit_adapters.voxformer.resnet import FPN, Bottleneck, ResNet50, frozen_fraction
from distilkit_adapters.voxformer.weights import SCOPE, from_torchvision

TORCHVISION_RESNET50_PARAMETERS = 25_557_032  # torchvision.models.resnet50(): its published parameter count


class Encoder(nn.Module):
    """The released network's image encoder under its names: ``img_backbone``, ``img_neck``."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.img_backbone = ResNet50()
        self.img_neck = FPN(1024, channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.img_neck(self.img_backbone(x))


def test_the_plane_is_voxformers_512_by_512_and_the_most_square_otherwise() -> None:
    assert plane_shape(128 * 128 * 16) == (512, 512)
    assert plane_shape(32 * 32 * 4) == (64, 64) and plane_shape(32 * 32 * 8) == (64, 128)
    assert plane_shape(2 * 3 * 2) == (3, 4) and plane_shape(7) == (1, 7)


def torchvision_file(encoder: Encoder, counters: bool = False) -> dict[str, torch.Tensor]:
    """A ResNet-50 state dict in torchvision's layout built from the encoder's backbone (names and shapes are
    torchvision's: the test checks the count of weights against torchvision's published one), with the fourth stage
    and the ImageNet classifier beside, and without the batch norms' counters unless ``counters``."""
    g = torch.Generator().manual_seed(5)
    state = {k: v.clone() for k, v in encoder.img_backbone.state_dict().items()}
    layer4 = nn.Sequential(Bottleneck(1024, 512, 2), Bottleneck(2048, 512, 1), Bottleneck(2048, 512, 1))
    state.update({f"layer4.{k}": v for k, v in layer4.state_dict().items()})
    fc = nn.Linear(2048, 1000)
    state.update({"fc.weight": fc.weight.detach(), "fc.bias": fc.bias.detach()})
    for key, value in state.items():  # weights and statistics unlike the initial ones (and of a sensible scale)
        if not value.is_floating_point():
            continue
        noise = torch.randn(value.shape, generator=g)
        if key.endswith("running_var"):
            state[key] = 1 + 0.2 * noise.abs()
        elif key.endswith(("running_mean", "bias")):
            state[key] = 0.1 * noise
        else:
            state[key] = value * (1 + 0.2 * noise)
    if not counters:
        state = {k: v for k, v in state.items() if not k.endswith("num_batches_tracked")}
    return state


def test_the_resnet50_has_torchvisions_names_and_size() -> None:
    encoder = Encoder(128)
    state = torchvision_file(encoder)
    weights = sum(v.numel() for k, v in state.items() if not k.endswith(("running_mean", "running_var")))
    assert weights == TORCHVISION_RESNET50_PARAMETERS
    assert {"conv1.weight", "bn1.running_var", "layer1.0.downsample.0.weight", "layer3.5.bn3.weight",
            "layer2.3.conv2.weight"} <= set(state)
    assert tuple(state["layer3.0.conv2.weight"].shape) == (256, 256, 3, 3)  # v1.5: the stride in the 3x3
    assert {"img_neck.lateral_convs.0.conv.weight", "img_neck.fpn_convs.0.conv.weight"} <= set(encoder.state_dict())
    image = torch.empty(1, 3, 370, 1220, device="meta")  # the shapes alone: the layers' own shape rules, no compute
    assert tuple(encoder.eval().to("meta")(image).shape) == (1, 128, 24, 77)  # VoxFormer's 370 x 1220 at stride 16


def test_a_torchvision_file_loads_into_the_encoder_and_computes_the_same(tmp_path) -> None:
    from distilkit_adapters.voxformer.adapter import VoxFormerAdapter

    torch.manual_seed(0)
    model = nn.Module()
    model.net = nn.Module()
    model.net = Encoder(16)
    file = torchvision_file(model.net)
    torch.save(file, tmp_path / "resnet50-19c8e357.pth")
    weights = VoxFormerAdapter.read_weights(str(tmp_path / "resnet50-19c8e357.pth"))
    assert isinstance(weights, PartialWeights) and weights.scope == SCOPE
    left = load_weights(model, weights, True, "init")
    assert left == ["ignored: fc.*", "ignored: layer4.*"]
    direct = Encoder(16)
    direct.img_backbone.load_state_dict({k: v for k, v in file.items() if not k.startswith(("fc.", "layer4."))},
                                        strict=False)
    direct.img_neck.load_state_dict(model.net.img_neck.state_dict())
    image = torch.rand(2, 3, 64, 96)
    assert torch.equal(model.net.eval()(image), direct.eval()(image))
    # a file with a misfit: each key named
    bad = dict(file)
    bad["layer2.1.conv2.weight"] = bad["layer2.1.conv2.weight"][:, :64]
    del bad["layer3.4.bn1.bias"]
    bad["layer3.9.conv1.weight"] = torch.zeros(1)
    with pytest.raises(DataError) as err:
        load_weights(model, from_torchvision(bad), True, "init x.pth")
    text = str(err.value)
    assert "net.img_backbone.layer2.1.conv2.weight (128, 64, 3, 3) (model: (128, 128, 3, 3))" in text
    assert "1 missing: net.img_backbone.layer3.4.bn1.bias" in text
    assert "1 unexpected: net.img_backbone.layer3.9.conv1.weight" in text


def test_batch_norms_and_the_first_stage_stay_frozen_in_training() -> None:
    torch.manual_seed(0)
    encoder = Encoder(16).train()
    backbone = encoder.img_backbone
    before = {k: v.clone() for k, v in backbone.state_dict().items()}
    out = encoder(torch.rand(2, 3, 64, 64))
    out.sum().backward()
    after = backbone.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)  # running statistics unchanged in train mode
    assert backbone.conv1.weight.grad is None and backbone.layer1[0].conv2.weight.grad is None
    assert backbone.bn1.weight.grad is None and backbone.layer3[0].bn1.weight.grad is None
    assert backbone.layer2[0].conv1.weight.grad is not None
    assert 0.02 < frozen_fraction(backbone) < 0.1


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    root = camera_kitti_copy(tmp_path_factory, "vf_kitti")  # the process's exported folder, copied: proposals added
    from distilkit.data import semantickitti as skio
    from distilkit.data.proposals import write_proposal

    for vox in sorted((root / "sequences").glob("*/voxels/*.bin")):  # proposals: the pooled occupancy, shifted
        occ = skio.read_voxel_bits(vox).reshape(128, 2, 128, 2, 16, 2).any(axis=(1, 3, 5))
        write_proposal(root / "proposals" / vox.parent.parent.name / "queries" / f"{vox.stem}.query_test",
                       np.roll(occ, 3, axis=0))
    return root


def test_proposals_are_read_from_a_folder_and_a_voxformer_stage_uses_them(folder, tmp_path) -> None:
    from distilkit.data import semantickitti as skio
    from distilkit.data.kitti_folder import SemanticKittiDataset
    from distilkit.data.lidar import collate_lidar
    from distilkit.data.params import SemanticKittiParams
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict

    params = SemanticKittiParams(root=str(folder), train=["00"], val=["08"], scale=4, proposals="proposals")
    data = SemanticKittiDataset(params, "val")
    sample = data[1]
    d, frame = data.items[1][:2]
    occ = np.roll(skio.read_voxel_bits(d / "voxels" / f"{frame:06d}.bin").reshape(128, 2, 128, 2, 16, 2)
                  .any(axis=(1, 3, 5)), 3, axis=0)
    expect = occ.reshape(32, 4, 32, 4, 4, 4).any(axis=(1, 3, 5))
    assert np.array_equal(sample["proposal"].astype(bool), expect) and expect.any() and not expect.all()
    batch = collate_lidar([sample, data[0]])
    assert tuple(batch.inputs["proposal"].shape) == (2, 32, 32, 4)

    recipe = {"schema_version": 1, "name": "cam", "seed": 0,
              "data": {"dataset": "semantickitti-ssc",
                       "params": {"root": str(folder), "train": ["00"], "val": ["08"], "scale": 4,
                                  "proposals": "proposals", "camera": {"height": 24, "width": 80}}},
              # about reading proposals from a folder, not a device's computation: the CPU whatever --device says
              "stages": {"camera": {"model": {"adapter": "voxformer"},
                                    "train": {"steps": 1, "batch_size": 2, "eval_every": 1, "device": "cpu"}}}}
    (camera,) = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    assert 0 <= camera.summary["test"]["best"]["miou"] <= 1

    missing = folder / "proposals" / "08" / "queries" / f"{frame:06d}.query_test"
    missing.rename(missing.with_name("moved"))
    try:
        with pytest.raises(DataError, match=rf"08/queries/{frame:06d}\.\*: missing \(proposals: proposals"):
            SemanticKittiDataset(params, "val")
    finally:
        missing.with_name("moved").rename(missing)


def test_the_paper_size_model_builds_and_trains_a_step_at_a_reduced_grid() -> None:
    from distilkit.data.batch import Batch
    from distilkit.data.camera import intrinsics, lidar_to_camera
    from distilkit.data.info import DataInfo
    from distilkit.data.params import CameraParams
    from distilkit.structures import VoxelGrid
    from distilkit_adapters.voxformer.adapter import VoxFormerAdapter, VoxFormerParams

    torch.manual_seed(0)
    cam = CameraParams(height=64, width=192)
    info = DataInfo(VoxelGrid.semantickitti(8), fields=frozenset({"image", "intrinsics", "lidar_to_camera",
                                                                   "voxel_target"}))
    params = VoxFormerParams(size="paper", geometry="ground-truth")
    model = VoxFormerAdapter(params, info)
    head = model.net.pts_bbox_head
    assert len(head.self_transformer.encoder.layers) == 2 and len(head.cross_transformer.encoder.layers) == 3
    assert head.self_transformer.encoder.layers[0].attentions[0].space == "plane"  # the released checkpoints'
    target = torch.randint(0, 20, (1, 32, 32, 4))
    batch = Batch({"image": torch.rand(1, 1, 3, 64, 192),
                   "intrinsics": torch.tensor(intrinsics(cam), dtype=torch.float32).view(1, 1, 3, 3),
                   "lidar_to_camera": torch.tensor(lidar_to_camera(0, 1.0), dtype=torch.float32).view(1, 1, 4, 4)},
                  {"voxel_target": target}, {"size": 1})
    out = model.train()(batch)
    assert tuple(out["logits"].shape) == (1, 20, 32, 32, 4) and tuple(out["image_features"].shape) == (1, 128, 4, 12)
    torch.nn.functional.cross_entropy(out["logits"], target).backward()
    assert head.self_transformer.encoder.layers[1].attentions[0].sampling_offsets.weight.grad is not None
    assert model.net.img_backbone.conv1.weight.grad is None
    missing = [n for n, p in model.named_parameters() if p.requires_grad and p.grad is None]
    assert not missing, missing[:5]
    with pytest.raises(ValueError, match="`widths` sizes the small encoder"):
        VoxFormerParams(size="paper", widths=[8, 16])
    with pytest.raises(ValueError, match="mixing: conv is the small stand-in's"):
        VoxFormerParams(size="paper", mixing="conv")
