"""Synthetic scenes, SemanticKITTI IO and collation."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import FIXTURES, TINY_DATA
from distilkit.data import semantickitti as sk
from distilkit.data.classes import CLASS_NAMES, NUM_CLASSES, ssc_lut
from distilkit.data.datasets import build_synthetic
from distilkit.data.kitti_folder import pool_labels
from distilkit.data.lidar import collate_lidar
from distilkit.data.params import SyntheticParams
from distilkit.data.raycast import Primitives, cast, ray_directions
from distilkit.data.synthetic import generate_split, make_sample, voxelize_majority
from distilkit.data.street_layout import make_scene
from distilkit.errors import DataError
from distilkit.geometry.voxel import VoxelGrid

P = SyntheticParams(**TINY_DATA)


def test_deterministic_per_seed_and_different_across_seeds() -> None:
    a, b, c = make_sample(5, P), make_sample(5, P), make_sample(6, P)
    for k in a:
        assert np.array_equal(a[k], b[k])
    assert not np.array_equal(a["voxel_label"], c["voxel_label"])


def test_scene_has_required_classes_static_and_moving_objects() -> None:
    rng = np.random.default_rng(0)
    scene = make_scene(rng, 0, 200, 1.0)
    prims = scene.prims
    labels = set(prims.box_label) | set(prims.cyl_label) | set(prims.sph_label)
    for raw in (48, 50, 51, 70, 71, 80, 252, 254):  # sidewalk, building, fence, vegetation, trunk, pole, moving car/person
        assert raw in labels
    moving = np.abs(prims.box_vel).sum(1) > 0
    assert moving.any() and (prims.box_inst[moving] > 0).all()
    inst = prims.box_inst[prims.box_inst > 0]
    assert len(np.unique(inst)) == len(inst)  # one id per object


def test_ray_caster_hits_a_box_at_the_right_distance() -> None:
    prims = Primitives(boxes=np.array([[10, -1, 0, 12, 1, 3]], np.float32), box_label=np.array([50]),
                       box_inst=np.array([0]), box_vel=np.zeros((1, 2), np.float32))
    dirs = np.array([[1, 0, 0], [0, 1, 0], [0.6, 0, -0.8]], np.float32)
    t, kind, idx, pts = cast(np.array([0, 0, 1.0], np.float32), dirs, prims)
    assert t[0] == pytest.approx(10.0) and kind[0] == 2
    assert kind[1] == 0 and not np.isfinite(t[1])
    assert kind[2] == 1 and pts[2, 2] == pytest.approx(0.0, abs=1e-5)  # ground
    assert ray_directions(4, 8, 2, -24).shape == (32, 3)


def test_sample_conventions() -> None:
    s = make_sample(1, P)
    grid = VoxelGrid.semantickitti(P.scale)
    assert s["voxel_label"].shape == grid.shape == (32, 32, 4)
    assert s["invalid"].shape == grid.shape
    assert set(np.unique(s["point_frame"])) == {0, 1}
    # labels are SSC train ids; the observed volume has road and empty space
    vals = set(np.unique(s["voxel_label"]).tolist())
    assert vals <= set(range(NUM_CLASSES)) | {255}
    assert 9 in vals and 0 in vals
    # occupied voxels are never invalid; invalid voxels exist (unobserved space)
    assert not (s["invalid"] & (s["voxel_label"] > 0)).any()
    assert s["invalid"].any() and (~s["invalid"]).any()
    # points of the current frame are in the sensor frame: ground about 1.73 m below the sensor
    cur = s["points"][(s["point_frame"] == 0) & (s["point_label"] == 9)]
    assert np.median(cur[:, 2]) == pytest.approx(-1.73, abs=0.1)


def test_majority_voxelisation_ties_to_smallest_id() -> None:
    grid = VoxelGrid((0.0, 0.0, 0.0), (2, 1, 1), 1.0)
    xyz = np.array([[0.5, 0.5, 0.5]] * 4 + [[1.5, 0.5, 0.5]] * 3, np.float32)
    raw = np.array([50, 50, 40, 40, 70, 70, 10])
    out = voxelize_majority(xyz, raw, grid)
    assert out[0, 0, 0] == 40 and out[1, 0, 0] == 70


def test_cache_is_reused(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("DISTILKIT_CACHE", str(tmp_path))
    a = generate_split(P, "val", 1)
    files = list(tmp_path.rglob("*.npz"))
    assert len(files) == 1
    mtime = files[0].stat().st_mtime_ns
    b = generate_split(P, "val", 1)
    assert files[0].stat().st_mtime_ns == mtime
    assert np.array_equal(a["points"], b["points"])


def test_a_corrupt_cache_entry_is_regenerated_not_trusted(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("DISTILKIT_CACHE", str(tmp_path))
    a = generate_split(P, "val", 1)
    (entry,) = tmp_path.rglob("*.npz")
    entry.write_bytes(entry.read_bytes()[: entry.stat().st_size // 2])  # a write cut short, a bad disk
    b = generate_split(P, "val", 1)
    assert np.array_equal(a["points"], b["points"]) and np.array_equal(a["voxel_label"], b["voxel_label"])
    with np.load(entry, allow_pickle=False) as z:  # written again, whole
        assert np.array_equal(z["points"], a["points"])


def test_collate_sets_invalid_to_ignore() -> None:
    ds = build_synthetic(P, "train")
    batch = collate_lidar([ds[0], ds[1]])
    assert batch.targets["voxel_label"].shape == (2, 32, 32, 4)
    assert (batch.targets["voxel_target"][batch.targets["invalid"]] == 255).all()
    assert int(batch.inputs["point_batch"].max()) == 1 and len(batch.inputs["points"]) == len(ds[0]["points"]) + len(ds[1]["points"])


def test_reads_the_real_semantickitti_scan() -> None:
    root = FIXTURES / "semantickitti-sample" / "sequences" / "00"
    pts = sk.read_points(root / "velodyne" / "000000.bin")
    sem, inst = sk.read_point_labels(root / "labels" / "000000.label", len(pts))
    assert pts.shape == (50, 4) and pts.dtype == np.float32
    assert set(np.unique(sem)) <= {0, 50, 52, 70, 71, 80} and (inst == 0).all()
    assert (ssc_lut()[sem] != 0).sum() > 0


def test_voxel_files_round_trip_and_bit_order(tmp_path) -> None:
    rng = np.random.default_rng(0)
    shape = (8, 4, 2)
    bits = rng.random(shape) < 0.3
    sk.write_voxel_bits(tmp_path / "a.invalid", bits)
    assert np.array_equal(sk.read_voxel_bits(tmp_path / "a.invalid", shape), bits)
    one = np.zeros(shape, bool)
    one.reshape(-1)[0] = True  # voxel 0 is the most significant bit of byte 0
    sk.write_voxel_bits(tmp_path / "b.bin", one)
    assert (tmp_path / "b.bin").read_bytes()[0] == 0x80
    labels = rng.integers(0, 260, shape).astype(np.uint16)
    sk.write_voxel_labels(tmp_path / "a.label", labels)
    assert np.array_equal(sk.read_voxel_labels(tmp_path / "a.label", shape), labels)


def test_corrupt_files_raise_clear_errors(tmp_path) -> None:
    (tmp_path / "x.bin").write_bytes(b"\x00" * 10)
    with pytest.raises(DataError, match="not a multiple of 16"):
        sk.read_points(tmp_path / "x.bin")
    with pytest.raises(DataError, match="not found"):
        sk.read_points(tmp_path / "missing.bin")
    (tmp_path / "y.label").write_bytes(b"\x00" * 8)
    with pytest.raises(DataError, match="expected"):
        sk.read_voxel_labels(tmp_path / "y.label", (4, 4, 4))


def test_pool_labels_majority_of_nonempty() -> None:
    lab = np.zeros((2, 2, 2), np.uint8)
    lab[0, 0, 0] = 9
    lab[1, 1, 1] = 9
    lab[0, 1, 0] = 13
    out, inv = pool_labels(lab, np.zeros_like(lab, bool), 2)
    assert out.shape == (1, 1, 1) and out[0, 0, 0] == 9 and not inv.any()


def _fake_kitti(tmp_path):
    """A SemanticKITTI-format folder: the real shared scan as frames 0 and 1, synthetic voxel files."""
    src = FIXTURES / "semantickitti-sample" / "sequences" / "00"
    seq = tmp_path / "sequences" / "08"
    for sub in ("velodyne", "labels", "voxels"):
        (seq / sub).mkdir(parents=True)
    for f in ("000000", "000001"):
        (seq / "velodyne" / f"{f}.bin").write_bytes((src / "velodyne" / "000000.bin").read_bytes())
        (seq / "labels" / f"{f}.label").write_bytes((src / "labels" / "000000.label").read_bytes())
    raw = np.zeros((256, 256, 32), np.uint16)
    raw[10:14, 100:104, 5:9] = 50   # building -> 13
    raw[0:4, 0:4, 0:4] = 52         # other-structure -> 255 (ignore)
    sk.write_voxel_labels(seq / "voxels" / "000000.label", raw)
    inv = np.zeros_like(raw, bool)
    inv[200:, :, :] = True
    sk.write_voxel_bits(seq / "voxels" / "000000.invalid", inv)
    eye = " ".join(["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0"])
    (seq / "calib.txt").write_text(f"P0: {eye}\nTr: {eye}\n")
    (seq / "poses.txt").write_text(f"{eye}\n1 0 0 1.0 0 1 0 0 0 0 1 0\n")
    return tmp_path


def test_semantickitti_folder_dataset(tmp_path) -> None:
    from distilkit.data.kitti_folder import SemanticKittiDataset
    from distilkit.data.params import SemanticKittiParams

    root = _fake_kitti(tmp_path)
    ds = SemanticKittiDataset(SemanticKittiParams(root=str(root), val=["08"], scale=4, input_frames=2), "val")
    assert len(ds) == 1
    s = ds[0]
    assert s["voxel_label"].shape == (64, 64, 8)
    assert s["voxel_label"][3, 25, 1] == 13 and s["voxel_label"][0, 0, 0] == 255
    assert s["invalid"][60].all() and not s["invalid"][10].any()
    p0, p1 = s["points"][s["point_frame"] == 0], s["points"][s["point_frame"] == 1]
    assert np.allclose(p1[:, 0], p0[:, 0] + 1.0) and np.allclose(p1[:, 1:], p0[:, 1:])
    with pytest.raises(DataError, match="sequences/00: missing .expected sequences/00/velodyne/\\*.bin and "
                                        "sequences/00/voxels/\\*.label") as err:
        SemanticKittiDataset(SemanticKittiParams(root=str(root)), "train")
    assert "sequences/10: missing" in str(err.value) and "sequences/08" not in str(err.value)
    (root / "sequences" / "08" / "poses.txt").unlink()
    (root / "sequences" / "08" / "velodyne" / "000000.bin").unlink()
    with pytest.raises(DataError) as err:
        SemanticKittiDataset(SemanticKittiParams(root=str(root), val=["08"], input_frames=2,
                                                 rectify=True), "val")
    lines = str(err.value).splitlines()
    assert lines[0].endswith("is not a complete SemanticKITTI folder:") and sorted(lines[1:]) == sorted([
        "  sequences/08/velodyne/000000.bin: missing (the scan of a labelled frame)",
        "  sequences/08/poses.txt: missing (fusing 2 scans needs it)"])


def _boxes_over_trajectory(scene, n_frames: int):
    for j in range(n_frames + 1):
        yield j, scene.prims.at_frame(j)


def test_traffic_never_overlaps_the_ego_car() -> None:
    from distilkit.data.street_layout import EGO_HALF_LENGTH, EGO_LANE_Y

    n_frames, speed = 11, 1.0
    for seed in range(60):
        rng = np.random.default_rng(seed)
        x0 = rng.uniform(0, 20)
        scene = make_scene(rng, x0 - 20, x0 + speed * n_frames + 80, speed, x0, n_frames)
        for j, prims in _boxes_over_trajectory(scene, n_frames):
            ego_x = x0 + speed * j
            b = prims.boxes
            hit = ((b[:, 0] < ego_x + EGO_HALF_LENGTH) & (b[:, 3] > ego_x - EGO_HALF_LENGTH)
                   & (b[:, 1] < EGO_LANE_Y + 0.9) & (b[:, 4] > EGO_LANE_Y - 0.9) & (b[:, 5] > 0.2))
            assert not hit.any(), f"scene seed {seed}, frame {j}: a box overlaps the ego car"
            c = prims.cylinders
            near = (np.abs(c[:, 0] - ego_x) < EGO_HALF_LENGTH + c[:, 4]) & (np.abs(c[:, 1] - EGO_LANE_Y) < 0.9 + c[:, 4])
            assert not near.any(), f"scene seed {seed}, frame {j}: a cylinder overlaps the ego car"


def test_ego_lane_traffic_does_appear_ahead() -> None:
    """The fix keeps traffic in the ego's lane (it only moves it out of the ego's way)."""
    from distilkit.data.street_layout import EGO_LANE_Y

    found = 0
    for seed in range(20):
        rng = np.random.default_rng(seed)
        scene = make_scene(rng, -20, 100, 1.0, 0.0, 11)
        b, vel = scene.prims.boxes, scene.prims.box_vel
        found += int((((b[:, 1] + b[:, 4]) / 2 - EGO_LANE_Y).__abs__() < 0.01).any() and (vel[:, 0] > 0).any())
    assert found >= 15


@pytest.mark.xdist_group("street")
def test_all_19_classes_occur_in_the_ground_truth() -> None:
    """Two street samples (shared with tests/test_rectify.py) hold every class in their voxel ground truth."""
    from _street_samples import SEEDS, street_sample

    seen = set()
    for seed in SEEDS:
        seen |= set(np.unique(street_sample(seed)["voxel_label"]).tolist())
    missing = [CLASS_NAMES[c] for c in range(1, NUM_CLASSES) if c not in seen]
    assert not missing, f"classes never in the voxel ground truth: {missing}"


def test_scribbles_are_sparse_consistent_and_distinguish_unlabelled_from_empty() -> None:
    from distilkit.data.classes import SCRIBBLE_UNLABELLED

    for mode in ("lines", "random"):
        s = make_sample(3, P.model_copy(update={"scribble": mode}))
        sc, vl, inv = s["scribble"], s["voxel_label"], s["invalid"]
        occupied = (vl != 0) & (vl != 255)
        labelled = (sc >= 1) & (sc < NUM_CLASSES)
        assert (sc[inv] == 255).all() and (sc[(vl == 0) & ~inv] == 0).all()
        assert set(np.unique(sc[occupied]).tolist()) <= set(range(1, NUM_CLASSES)) | {SCRIBBLE_UNLABELLED}
        assert 0 < labelled.sum() < occupied.sum()  # some, not all, occupied voxels carry a class
        assert (sc == SCRIBBLE_UNLABELLED).any()
        agree = (sc[labelled] == vl[labelled]).mean()
        assert agree > 0.6, f"{mode}: scribble classes agree with the dense labels on only {agree:.0%}"


def test_scribbles_travel_through_collate_and_reach_rgo2d() -> None:
    import torch

    from distilkit.data.classes import SCRIBBLE_UNLABELLED
    from distilkit.losses import rgo2d
    from distilkit.objectives.region import RGO2D, RGO2DParams

    samples = [make_sample(i, P) for i in range(2)]
    batch = collate_lidar(samples)
    assert batch.targets["scribble"].shape == batch.targets["voxel_label"].shape
    assert torch.equal(batch.targets["scribble"][1], torch.from_numpy(samples[1]["scribble"].astype(np.int64)))
    g = torch.Generator().manual_seed(0)
    shape = (2, NUM_CLASSES, *batch.targets["voxel_label"].shape[1:])
    s, t = torch.randn(shape, generator=g), torch.randn(shape, generator=g)
    occ = (batch.targets["voxel_target"] != 0) & (batch.targets["voxel_target"] != 255)
    obj = RGO2D(RGO2DParams())
    value = obj.compute({"student": s, "teacher": t, **obj.batch_roles(batch)}, batch)
    assert obj.batch_roles(batch)["labels"] is batch.targets["scribble"]  # the first candidate the data has
    assert torch.allclose(value, rgo2d(s, t, batch.targets["scribble"], occ))
    dense = rgo2d(s, t, batch.targets["voxel_target"], occ)
    assert not torch.allclose(value, dense)  # the scribbles, not the dense labels, are used
    # unlabelled voxels (254) are no class: relabelling them as empty leaves the loss unchanged
    as_empty = batch.targets["scribble"].masked_fill(batch.targets["scribble"] == SCRIBBLE_UNLABELLED, 0)
    assert torch.allclose(value, rgo2d(s, t, as_empty, occ))
