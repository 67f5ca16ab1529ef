"""The camera of a SemanticKITTI folder (image_2/, calib.txt's P2 and Tr): reading, calibration, resizing, sparse
depth, the exported synthetic camera read back, and a camera model trained on the folder."""

from __future__ import annotations

import numpy as np
import pytest

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from distilkit.data import kitti_camera as kc


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """This process's exported folder with 24 x 80 camera images (tests/_camera_kitti.py: ``export-kitti --frames 11
    --camera`` with conftest's EXPORT_SET and ``camera={height: 24, width: 80}``), shared with the other modules that
    read it: read only (a test that changes files works on a copy)."""
    from _camera_kitti import camera_kitti

    return camera_kitti(tmp_path_factory)


def test_images_round_trip_exactly(tmp_path) -> None:
    image = np.random.default_rng(0).integers(0, 256, (7, 11, 3), dtype=np.uint8)
    kc.write_image(tmp_path / "a.png", image)
    assert np.array_equal(kc.read_image(tmp_path / "a.png"), image)


def test_cam2_calibration_projects_as_kittis_p2_tr() -> None:
    """K · (T · X) equals KITTI's P2 · Tr · X for a P2 with cam2's baseline in its last column."""
    rng = np.random.default_rng(1)
    k = np.array([[718.9, 0.0, 607.2], [0.0, 718.9, 185.2], [0.0, 0.0, 1.0]])
    p2 = np.hstack([k, k @ np.array([[0.06], [-0.003], [0.003]])])
    tr = np.eye(4)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    tr[:3, :3], tr[:3, 3] = q, rng.normal(size=3)
    calib = {"P2": np.vstack([p2, [0, 0, 0, 1]]), "Tr": tr}
    kk, t = kc.cam2_calibration(calib)
    x = np.append(rng.normal(size=3) * 10, 1.0)
    assert np.allclose(kk @ (t @ x)[:3], p2 @ tr @ x)
    with pytest.raises(Exception, match="P2"):
        kc.cam2_calibration({"Tr": tr})


def test_resizing_scales_the_intrinsics_with_the_pixel_centres() -> None:
    k = np.array([[50.0, 0.0, 31.5], [0.0, 40.0, 11.5], [0.0, 0.0, 1.0]])
    image = np.zeros((24, 64, 3), np.uint8)
    out, k2 = kc.resize(image, k, 12, 16)
    assert out.shape == (12, 16, 3)
    point = np.array([0.3, -0.2, 4.0])
    u, v = (k @ point)[:2] / point[2]
    u2, v2 = (k2 @ point)[:2] / point[2]
    # the same point at the same place of the picture: pixel centre i + 0.5 scales with the image
    assert np.isclose((u2 + 0.5) / 16, (u + 0.5) / 64) and np.isclose((v2 + 0.5) / 12, (v + 0.5) / 24)
    same, k3 = kc.resize(image, k, 24, 64)
    assert same is image and k3 is k


def test_sparse_depth_equals_a_naive_nearest_point_per_pixel() -> None:
    rng = np.random.default_rng(2)
    xyz = np.c_[rng.uniform(-5, 30, 400), rng.uniform(-10, 10, 400), rng.uniform(-2, 2, 400)]
    k = np.array([[20.0, 0.0, 16.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]])
    t = np.eye(4)
    t[:3, :3] = [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]
    got = kc.sparse_depth(xyz, k, t, 12, 32, 25.0)
    want = np.zeros((12, 32))
    for p in xyz:
        c = t[:3, :3] @ p + t[:3, 3]
        if not 1e-3 < c[2] <= 25.0:
            continue
        u, v = int(np.floor(k[0, 0] * c[0] / c[2] + k[0, 2])), int(np.floor(k[1, 1] * c[1] / c[2] + k[1, 2]))
        if 0 <= u < 32 and 0 <= v < 12 and (want[v, u] == 0 or c[2] < want[v, u]):
            want[v, u] = c[2]
    assert (want > 0).sum() > 10 and np.allclose(got, want, atol=1e-5)


def test_the_exported_camera_reads_back_as_the_synthetic_one(exported) -> None:
    """Images equal the synthetic renderer's; the intrinsics and each frame's LiDAR -> camera transform (through
    calib.txt and the poses) equal the synthetic camera's formulas; depth is the scan projected."""
    from distilkit.data.camera import intrinsics, lidar_to_camera
    from distilkit.data.kitti_folder import SemanticKittiDataset
    from distilkit.data.params import CameraParams, SemanticKittiParams

    params = SemanticKittiParams(root=str(exported), train=["00"], val=["08"], scale=4, occluded=True,
                                 camera={"height": 24, "width": 80, "previous": [3, 7]})
    ds = SemanticKittiDataset(params, "val")
    s = ds[1]  # frame 5: images of frames 5, 2 and 0 (5 - 7 < 0 repeats the first)
    seq = exported / "sequences" / "08"
    for i, j in enumerate((5, 2, 0)):
        assert np.array_equal(s["image"][i], kc.read_image(seq / "image_2" / f"{j:06d}.png"))
    cp = CameraParams(height=24, width=80)
    assert np.allclose(s["intrinsics"], intrinsics(cp), atol=1e-4)
    for i, back in enumerate((0, 3, 5)):
        assert np.allclose(s["lidar_to_camera"][i], lidar_to_camera(back, 1.0), atol=1e-5)
    assert s["depth"].shape == (24, 80) and 0 < (s["depth"] > 0).mean() < 1
    assert s["occluded"].shape == (64, 64, 8)
    assert ds.info.cameras[0].depth == "sparse" and ds.info.cameras[0].frames == (0, -3, -7)


def test_occluded_masks_are_hidden_from_the_current_viewpoint(exported) -> None:
    from distilkit.data import semantickitti as sk

    seq = exported / "sequences" / "08" / "voxels"
    occ, inv = sk.read_voxel_bits(seq / "000005.occluded"), sk.read_voxel_bits(seq / "000005.invalid")
    now = sk.read_voxel_bits(seq / "000005.bin")
    assert not (occ & now).any() and (inv <= occ).all() and occ.sum() > inv.sum()


def test_missing_and_corrupt_images_are_named(exported, tmp_path) -> None:
    import shutil

    from distilkit.data.kitti_folder import SemanticKittiDataset
    from distilkit.data.params import SemanticKittiParams
    from distilkit.errors import DataError

    root = tmp_path / "k"
    shutil.copytree(exported / "sequences" / "08", root / "sequences" / "08")
    (root / "sequences" / "08" / "image_2" / "000010.png").unlink()
    params = SemanticKittiParams(root=str(root), train=["08"], val=None, camera={"height": 24, "width": 80})
    with pytest.raises(DataError, match=r"sequences/08/image_2/000010.png: missing"):
        SemanticKittiDataset(params, "train")
    (root / "sequences" / "08" / "image_2" / "000010.png").write_bytes(b"not a png")
    with pytest.raises(DataError, match=r"000010.png: not a readable image"):
        SemanticKittiDataset(params, "train")[2]


def test_a_camera_model_trains_on_the_folder(exported, tmp_path, device) -> None:
    """A proposal stage and a VoxFormer on its proposals, a step of two scenes each, on every 10th scan (the voxel
    frames 0 and 10 of each sequence: two scenes to train on and two to score)."""
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict

    recipe = {"schema_version": 1, "name": "cam", "seed": 0,
              "data": {"dataset": "semantickitti-ssc",
                       "params": {"root": str(exported), "train": ["00"], "val": ["08"], "scale": 4, "stride": 10,
                                  "camera": {"height": 24, "width": 80}}},
              "stages": {"proposal": {"model": {"adapter": "voxformer-proposal"},  # a step of 2 scenes each
                                      "train": {"steps": 1, "batch_size": 2, "eval_every": 1, "metric": "iou",
                                                "device": device.type}},
                         "camera": {"model": {"adapter": "voxformer"}, "aux": {"proposal": {"from": "proposal"}},
                                    "train": {"steps": 1, "batch_size": 2, "eval_every": 1, "device": device.type}}}}
    proposal, camera = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    assert 0 <= camera.summary["test"]["best"]["miou"] <= 1 and camera.summary["report_split"] == "val"
    assert np.isfinite(proposal.summary["test"]["best"]["iou"])


def test_depth_l1_leaves_unknown_pixels_out_on_sparse_lidar_depth() -> None:
    """On a rendered (dense) depth map 0 is sky and counts as sky_depth; on a folder's sparse LiDAR depth 0 is
    unknown and never counts."""
    import dataclasses

    import torch

    from distilkit.data.batch import Batch
    from distilkit.data.camera import rig
    from distilkit.data.info import DataInfo
    from distilkit.data.params import CameraParams
    from distilkit.losses.task import DepthL1
    from distilkit.term import TermContext

    target = torch.tensor([[[0.0, 10.0], [20.0, 0.0]]])
    pred = torch.tensor([[[5.0, 12.0], [20.0, 40.0]]])
    dense = rig(CameraParams(), 0.0)
    got = {}
    for kind in ("dense", "sparse"):
        term = DepthL1(DepthL1.Params(sky_depth=80.0))
        info = DataInfo(None, cameras=(dataclasses.replace(dense, depth=kind),))
        term.bind(TermContext(student=torch.nn.Identity(), teacher=None, device=torch.device("cpu"), info=info))
        got[kind] = float(term.compute({"student": pred, "target": target}, Batch({}, {}, {})))
    assert got["dense"] == pytest.approx((75 + 2 + 0 + 40) / 4) and got["sparse"] == pytest.approx((2 + 0) / 2)
