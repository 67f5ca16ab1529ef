"""SCPNet's label rectification (Algorithm 1) as the paper intends it: against a naive loop of the pseudocode, each
of the released code's three bugs absent, and the traces of moving cars removed from synthetic completion labels."""

from __future__ import annotations

import numpy as np
import pytest

from distilkit.data.classes import CLASS_NAMES, LEARNING_MAP_INV
from distilkit.data.rectify import DEFAULT_DYNAMIC, dynamic_ids, rectify
from distilkit.structures import VoxelGrid

GRID = VoxelGrid((0.0, 0.0, 0.0), (12, 10, 6), 1.0)
CAR, PERSON, ROAD = CLASS_NAMES.index("car"), CLASS_NAMES.index("person"), CLASS_NAMES.index("road")


def raw(train_id: int, instance: int) -> int:
    return LEARNING_MAP_INV[train_id] | (instance << 16)


def centre(i: int, j: int, k: int) -> list[float]:
    return [i + 0.5, j + 0.5, k + 0.5]


def naive_algorithm_1(labels: np.ndarray, xyz: np.ndarray, point_raw: np.ndarray, classes: list[int]) -> np.ndarray:
    """SCPNet's pseudocode line by line with Python sets (getInd, bound per instance inclusive, difference)."""
    out = labels.copy()
    sem = np.array([{v: k for k, v in LEARNING_MAP_INV.items()}.get(int(r) & 0xFFFF, 0) for r in point_raw])
    inst = point_raw.astype(np.int64) >> 16
    vox = [tuple(int(v) for v in np.floor(p)) for p in xyz]
    for c in classes:
        p_c = {tuple(v) for v in np.argwhere(labels == c)}
        l_p = [(inst[n], vox[n]) for n in range(len(xyz)) if sem[n] == c]
        if not l_p:
            dif = p_c
        elif p_c:
            inside: set[tuple[int, ...]] = set()
            for d in {i for i, _ in l_p}:
                m = np.array([v for i, v in l_p if i == d])
                lo, hi = m.min(0), m.max(0)
                inside |= {(a, b, e) for a in range(lo[0], hi[0] + 1) for b in range(lo[1], hi[1] + 1)
                           for e in range(lo[2], hi[2] + 1)}
            dif = p_c - inside
        else:
            dif = set()
        for v in dif:
            out[v] = 255
    return out


def test_rectification_equals_the_papers_algorithm_on_random_scenes() -> None:
    rng = np.random.default_rng(0)
    for trial in range(5):
        labels = rng.choice([0, CAR, PERSON, ROAD], size=GRID.shape, p=[0.7, 0.12, 0.08, 0.1]).astype(np.uint8)
        n = 40
        xyz = rng.uniform(0, [12, 10, 6], size=(n, 3))
        classes = rng.choice([CAR, PERSON, ROAD], size=n)
        point_raw = np.array([raw(int(c), int(rng.integers(1, 4))) for c in classes], np.uint32)
        if trial == 4:  # no person point at all: every person voxel goes
            point_raw[classes == PERSON] = raw(ROAD, 0)
        got = rectify(labels, xyz, point_raw, GRID, [CAR, PERSON])
        assert np.array_equal(got, naive_algorithm_1(labels, xyz, point_raw, [CAR, PERSON]))
        assert np.array_equal(got[labels == ROAD], labels[labels == ROAD])  # a static class is never touched


def test_instances_are_the_high_16_bits_not_the_semantic_id() -> None:
    """Released bug 1: with ``label & 0xFFFF`` as the instance, one box spans both cars and keeps the trace between."""
    labels = np.zeros(GRID.shape, np.uint8)
    labels[1:11, 4, 0] = CAR  # car A at x = 1, car B at x = 10, a trace of car A in between
    xyz = np.array([centre(1, 4, 0), centre(10, 4, 0)])
    out = rectify(labels, xyz, np.array([raw(CAR, 1), raw(CAR, 2)], np.uint32), GRID, [CAR])
    assert out[1, 4, 0] == CAR and out[10, 4, 0] == CAR and (out[2:10, 4, 0] == 255).all()


def test_a_one_voxel_thick_object_keeps_its_voxel() -> None:
    """Released bug 2: ``[min:max)`` slicing gives a one-voxel-thick instance an empty box, wiping it."""
    labels = np.zeros(GRID.shape, np.uint8)
    labels[3, 3, 2] = PERSON
    out = rectify(labels, np.array([centre(3, 3, 2)]), np.array([raw(PERSON, 7)], np.uint32), GRID, [PERSON])
    assert out[3, 3, 2] == PERSON


def test_a_class_without_points_loses_its_voxels_and_nothing_else() -> None:
    """Released bug 3: an int 0/1 'mask' indexes x-slices 0 and 1 instead of the class's voxels."""
    labels = np.full(GRID.shape, ROAD, np.uint8)
    labels[5, 5, 1] = PERSON
    out = rectify(labels, np.array([centre(0, 0, 0)]), np.array([raw(ROAD, 0)], np.uint32), GRID, [PERSON])
    assert out[5, 5, 1] == 255 and (out[:2] == ROAD).all() and (out == ROAD).sum() == labels.size - 1


def test_classes_by_name_and_bad_input_are_named() -> None:
    assert dynamic_ids(DEFAULT_DYNAMIC) == [1, 4, 5, 6, 7, 8]  # SCPNet's dynamic_classes
    with pytest.raises(ValueError, match="'lorry'"):
        dynamic_ids(["lorry"])
    with pytest.raises(ValueError, match="do not fit the grid"):
        rectify(np.zeros((3, 3, 3), np.uint8), np.zeros((0, 3)), np.zeros(0, np.uint32), GRID)


@pytest.mark.xdist_group("street")
def test_the_traces_of_moving_cars_in_synthetic_completion_labels_are_removed() -> None:
    """The synthetic street's completion labels fuse the current scan with the next 10: moving cars leave traces.
    Rectified with the current scan's panoptic labels, most car voxels of moving instances outside their current box
    go, and every voxel of a static class stays (two street samples on 0.8 m voxels, shared with tests/test_data.py)."""
    from _street_samples import SEEDS, STREET, street_sample

    removed, before = 0, 0
    for seed in SEEDS:
        s = street_sample(seed)
        labels = s["voxel_label"]
        current = s["point_frame"] == 0
        out = rectify(labels, s["points"][current, :3], s["point_raw"][current], VoxelGrid.semantickitti(STREET.scale))
        dynamic = np.isin(labels, dynamic_ids(DEFAULT_DYNAMIC))
        assert np.array_equal(out[~dynamic], labels[~dynamic])
        before += int(dynamic.sum())
        removed += int((out[dynamic] == 255).sum())
    assert before > 0 and 0 < removed < before


def _kitti_folder(root):
    """One sequence, one frame, in SemanticKITTI's layout: a car seen at x = 10-12 m whose completion labels carry a
    trace back to x = 4 m, a building, and a person without any point in the scan."""
    from distilkit.data import semantickitti as sk

    seq = root / "sequences" / "08"
    for sub in ("velodyne", "labels", "voxels"):
        (seq / sub).mkdir(parents=True)
    grid = VoxelGrid.semantickitti(1)
    xyz = np.array([[x, 0.1, -1.0] for x in np.arange(10.1, 12.0, 0.2)] + [[20.0, 5.0, 0.0]], np.float32)
    sem = np.array([252] * (len(xyz) - 1) + [50])  # a moving car (raw 252), a building point
    inst = np.array([3] * (len(xyz) - 1) + [0])
    np.concatenate([xyz, np.zeros((len(xyz), 1), np.float32)], 1).tofile(seq / "velodyne" / "000000.bin")
    sk.write_point_labels(seq / "labels" / "000000.label", sem, inst)
    raw = np.zeros(grid.shape, np.uint16)
    iy, iz = int((0.1 + 25.6) / 0.2), int((-1.0 + 2.0) / 0.2)
    raw[20:60, iy, iz] = 10                      # car voxels from x = 4 m (the trace) to 12 m
    raw[100, int((5.0 + 25.6) / 0.2), 10] = 50   # building
    raw[30, 30, 3] = 30                          # a person no point of the scan shows
    sk.write_voxel_labels(seq / "voxels" / "000000.label", raw)
    sk.write_voxel_bits(seq / "voxels" / "000000.invalid", np.zeros(grid.shape, bool))
    eye = " ".join(["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0"])
    (seq / "calib.txt").write_text(f"P0: {eye}\nTr: {eye}\n")
    (seq / "poses.txt").write_text(f"{eye}\n")
    return seq, (iy, iz)


def test_data_rectify_writes_beside_the_originals_and_the_dataset_reads_either(tmp_path, capsys) -> None:
    from distilkit.cli import main
    from distilkit.data.kitti_folder import SemanticKittiDataset
    from distilkit.data.params import SemanticKittiParams

    seq, (iy, iz) = _kitti_folder(tmp_path)
    original = (seq / "voxels" / "000000.label").read_bytes()
    assert main(["data", "rectify", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "car: 10 of 40 voxels left (25.0 % left)" in out and "person: 0 of 1 voxels left" in out
    assert (seq / "voxels" / "000000.label").read_bytes() == original  # untouched
    on_the_fly = SemanticKittiDataset(SemanticKittiParams(root=str(tmp_path), val=["08"], rectify=True), "val")
    written = SemanticKittiDataset(SemanticKittiParams(root=str(tmp_path), val=["08"],
                                                       voxels="voxels_rectified"), "val")
    plain = SemanticKittiDataset(SemanticKittiParams(root=str(tmp_path), val=["08"]), "val")
    a, b, c = on_the_fly[0]["voxel_label"], written[0]["voxel_label"], plain[0]["voxel_label"]
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert (a[50:60, iy, iz] == CAR).all() and (a[20:50, iy, iz] == 255).all() and a[30, 30, 3] == 255
    assert a[100, int((5.0 + 25.6) / 0.2), 10] == CLASS_NAMES.index("building")
    (seq / "labels" / "000000.label").unlink()
    assert main(["data", "rectify", str(tmp_path)]) == 2
    assert "needs the scan's point labels" in capsys.readouterr().err


def test_a_semanticposs_folder_is_rectified_with_its_own_table(tmp_path, capsys) -> None:
    """SemanticPOSS raw ids (car = 7, building = 15): its moving classes by default, its raw ids written back."""
    from distilkit.cli import main
    from distilkit.data import semantickitti as sk

    seq = tmp_path / "sequences" / "02"
    for sub in ("velodyne", "labels", "voxels"):
        (seq / sub).mkdir(parents=True)
    xyz = np.array([[10.1, 0.1, -1.0], [10.3, 0.1, -1.0]], np.float32)
    np.concatenate([xyz, np.zeros((2, 1), np.float32)], 1).tofile(seq / "velodyne" / "000000.bin")
    sk.write_point_labels(seq / "labels" / "000000.label", np.array([7, 7]), np.array([1, 1]))
    raw = np.zeros((256, 256, 32), np.uint16)
    iy, iz = int((0.1 + 25.6) / 0.2), int((-1.0 + 2.0) / 0.2)
    raw[40:52, iy, iz] = 7   # the car at x = 10.0-10.4 m and its trace from x = 8 m
    raw[100, 100, 10] = 15  # building
    sk.write_voxel_labels(seq / "voxels" / "000000.label", raw)
    assert main(["data", "rectify", str(tmp_path), "--labels", "semanticposs"]) == 0
    assert "car: 2 of 12 voxels left" in capsys.readouterr().out
    out = sk.read_voxel_labels(seq / "voxels_rectified" / "000000.label")
    assert out[50, iy, iz] == 7 and out[51, iy, iz] == 7 and (out[40:50, iy, iz] == 1).all() and out[100, 100, 10] == 15
