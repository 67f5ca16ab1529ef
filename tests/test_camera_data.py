"""The synthetic streets' camera: images and depth cast from the same street as the LiDAR scans, calibration that
maps the LiDAR frame into each frame's camera, and a camera that changes no LiDAR array and no LiDAR stage."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import TINY_DATA, tiny_recipe
from distilkit.data.camera import intrinsics, lidar_to_camera
from distilkit.data.datasets import build_synthetic, collate_street, synthetic_info
from distilkit.data.params import CameraParams, SyntheticParams
from distilkit.data.raycast import Primitives, cast
from distilkit.data.render import make_camera_sample, pixel_rays, render, surface_normals
from distilkit.data.synthetic import generate_split, make_sample, street
from distilkit.structures import VoxelGrid

CAMERA = {"height": 24, "width": 80, "previous": [3]}


def backproject(depth: np.ndarray, k: np.ndarray, to_camera: np.ndarray) -> np.ndarray:
    """(M, 3) LiDAR-frame points of the pixels with a depth, by the pinhole model written out per pixel."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    cam = np.stack([(u + 0.5 - k[0, 2]) / k[0, 0] * z, (v + 0.5 - k[1, 2]) / k[1, 1] * z, z, np.ones_like(z)], 1)
    return (np.linalg.inv(to_camera) @ cam.T).T[:, :3]


def occupied_near(points: np.ndarray, labels: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    """Whether each point's voxel or one of its 26 neighbours is occupied (points inside the grid and below the
    LiDAR's highest beam, which looks 2 degrees up from 1.73 m: a camera sees facades and crowns above it)."""
    idx = np.floor((points - np.array(grid.origin)) / grid.voxel_size).astype(int)
    inside = ((idx >= 1) & (idx < np.array(grid.shape) - 1)).all(1) & (points[:, 2] < 1.0)
    occ = (labels != 0) & (labels != 255)
    hits = np.zeros(inside.sum(), bool)
    for d in np.ndindex(3, 3, 3):
        j = idx[inside] + np.array(d) - 1
        hits |= occ[j[:, 0], j[:, 1], j[:, 2]]
    return hits


@pytest.mark.parametrize("frames_back", [0, 3])
def test_the_camera_sees_the_surfaces_the_lidar_voxelised(frames_back: int) -> None:
    """Pixels back-projected with their depth and the calibration of their frame land on the voxels the LiDAR
    scans fill (the same street; earlier frames through their own calibration)."""
    p = SyntheticParams(**{**TINY_DATA, "scale": 4, "gt_frames": 6}, camera=CAMERA)
    seed = 11
    lidar = make_sample(seed, p)
    _, scene, ego = street(seed, p)
    _, depth = render(scene, ego, -frames_back, p.camera, p.ego_speed, np.random.default_rng(0))
    points = backproject(depth, intrinsics(p.camera), lidar_to_camera(frames_back, p.ego_speed))
    near = occupied_near(points, lidar["voxel_label"], VoxelGrid.semantickitti(4))
    assert near.size > 200
    assert near.mean() > 0.9, near.mean()
    # a wrong calibration does not: the same depths through the current camera, when they came from an earlier one
    if frames_back:
        wrong = occupied_near(backproject(depth, intrinsics(p.camera), lidar_to_camera(0, p.ego_speed)),
                              lidar["voxel_label"], VoxelGrid.semantickitti(4))
        assert wrong.mean() < near.mean() - 0.1


def test_samples_carry_images_depth_and_calibration_per_frame() -> None:
    p = SyntheticParams(**TINY_DATA, camera=CAMERA)
    s = make_camera_sample(5, p)
    assert s["image"].shape == (2, 24, 80, 3) and s["image"].dtype == np.uint8
    assert s["depth"].shape == (24, 80) and (s["depth"] >= 0).all() and (s["depth"] <= 80).all()
    assert (s["depth"] > 0).mean() > 0.3  # the lower half sees the road
    np.testing.assert_allclose(s["lidar_to_camera"][1], lidar_to_camera(3, p.ego_speed), atol=1e-6)
    # the image is shaded: not one flat colour per class
    assert len(np.unique(s["image"].reshape(-1, 3), axis=0)) > 100
    again = make_camera_sample(5, p)
    assert all(np.array_equal(s[k], again[k]) for k in s)


def test_a_camera_changes_no_lidar_array_and_batches_its_fields() -> None:
    plain = SyntheticParams(**TINY_DATA)
    with_camera = SyntheticParams(**TINY_DATA, camera=CAMERA)
    a, b = generate_split(plain, "val", 1), generate_split(with_camera, "val", 1)
    assert set(a) == set(b) and all(np.array_equal(a[k], b[k]) for k in a)
    ds = build_synthetic(with_camera, "train")
    batch = collate_street([ds[0], ds[1]])
    assert batch.inputs["image"].shape == (2, 2, 3, 24, 80) and batch.inputs["image"].max() <= 1.0
    assert batch.inputs["intrinsics"].shape == (2, 2, 3, 3) and batch.inputs["lidar_to_camera"].shape == (2, 2, 4, 4)
    assert batch.targets["depth"].shape == (2, 24, 80)
    info = synthetic_info(with_camera)
    assert {"image", "depth", "intrinsics", "lidar_to_camera"} <= info.fields
    assert info.cameras[0].size == (24, 80) and info.cameras[0].frames == (0, -3)
    assert "image" not in synthetic_info(plain).fields and collate_street([build_synthetic(plain, "val")[0]]).inputs.keys() \
        == {"points", "point_batch", "point_frame"}


def test_surface_normals_face_the_ray() -> None:
    prims = Primitives(boxes=np.array([[5, -1, 0, 7, 1, 2]], np.float32), box_label=np.array([50]),
                       box_inst=np.array([0]), box_vel=np.zeros((1, 2), np.float32),
                       spheres=np.array([[5, 6, 1, 1]], np.float32), sph_label=np.array([70]), sph_inst=np.array([0]),
                       sph_vel=np.zeros((1, 2), np.float32))
    dirs = np.array([[1, 0, 0], [1, 1.2, 0], [0, 0, -1]], np.float32)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origin = np.array([0, 0, 1], np.float32)
    t, kind, index, xyz = cast(origin, dirs, prims)
    n = surface_normals(prims, kind, index, xyz)
    np.testing.assert_allclose(n[0], [-1, 0, 0], atol=1e-6)  # the box's near face
    assert kind[1] == 4 and np.isclose(np.linalg.norm(n[1]), 1) and n[1] @ dirs[1] < 0  # the sphere, facing us
    np.testing.assert_allclose(n[2], [0, 0, 1])  # the ground
    cam, lidar = pixel_rays(CameraParams(height=8, width=8))
    np.testing.assert_allclose(np.linalg.norm(lidar, axis=1), 1, rtol=1e-6)
    assert (lidar[:, 0] > 0.5).all() and (cam[:, 2] > 0.5).all()  # every pixel looks forward


def test_adding_a_camera_retrains_only_the_stages_that_read_it(monkeypatch) -> None:
    """A stage's identity holds the camera's parameters and version only when the stage reads a camera field."""
    from distilkit.data.info import FieldGroup
    from distilkit.engine.store import identity
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.recipe import recipe_from_dict
    from distilkit.registry import DATASETS

    def resolved(camera: dict | None):
        r = tiny_recipe(distill=False)
        if camera is not None:
            r["data"]["params"]["camera"] = camera
        return resolve(recipe_from_dict(r))

    plain, res = resolved(None), resolved(CAMERA)
    lidar_only = identity.stage_hashes(plain)[0]["teacher"]
    assert identity.stage_hashes(res)[0]["teacher"] == lidar_only  # SCPNet reads no camera field
    stage = res.stages["teacher"]
    assert "image" not in identity.stage_reads(res, stage) and "points" in identity.stage_reads(res, stage)

    entry = DATASETS.entry("synthetic-lidar")
    monkeypatch.setattr(identity, "stage_reads", lambda res, stage: frozenset({"points", "depth"}))
    reader = identity.stage_identity(res, stage, {})
    assert reader != lidar_only  # reading the depth map: the camera's parameters count
    other_camera = resolved({**CAMERA, "height": 32})
    assert identity.stage_identity(other_camera, other_camera.stages["teacher"], {}) != reader
    monkeypatch.setitem(entry.meta, "field_groups", {"camera": FieldGroup(frozenset({"depth"}), 99)})
    assert identity.stage_identity(res, stage, {}) != reader  # and so does the camera code's version
    monkeypatch.setattr(identity, "stage_reads", lambda res, stage: frozenset({"points"}))
    assert identity.stage_identity(res, stage, {}) == lidar_only  # which a LiDAR stage never sees
