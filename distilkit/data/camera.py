"""The camera of the synthetic streets: a pinhole rig like KITTI's left colour camera, and the batch fields it adds.

Batch fields (every frame's calibration is a per-sample tensor, so a model needs nothing beyond the batch):

* inputs ``image`` (B, T, 3, H, W) float in 0..1: the current frame first, then the earlier frames the data gives
  (``CameraParams.previous``); ``intrinsics`` (B, T, 3, 3) pixels; ``lidar_to_camera`` (B, T, 4, 4): points of the
  *current* LiDAR frame (the frame of the voxel grid) to each frame's camera (x right, y down, z forward);
* target ``depth`` (B, H, W) metres along the current camera's z axis (0: nothing within ``max_depth``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from distilkit.data.batch import Batch
from distilkit.data.info import Camera
from distilkit.data.params import CameraParams

if TYPE_CHECKING:
    import torch

CAMERA_INPUTS = frozenset({"image", "intrinsics", "lidar_to_camera"})
CAMERA_TARGETS = frozenset({"depth"})
CAMERA_FIELDS = CAMERA_INPUTS | CAMERA_TARGETS

# KITTI odometry, sequence 00, P2 and Tr (rounded): 1241 x 376 pixels
KITTI_SIZE = (376, 1241)
KITTI_FOCAL = 718.856
KITTI_CENTRE = (607.19, 185.22)  # (cx, cy)
CAMERA_IN_LIDAR = np.array([0.27, 0.06, -0.08])  # cam2's centre in the LiDAR frame (metres): ahead, left, below
LIDAR_TO_CAMERA_AXES = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # x fwd,y left,z up -> x r,y d,z f


def intrinsics(p: CameraParams) -> np.ndarray:
    """(3, 3) pinhole matrix of KITTI's cam2 scaled to the image size (square pixels kept per axis)."""
    sy, sx = p.height / KITTI_SIZE[0], p.width / KITTI_SIZE[1]
    return np.array([[KITTI_FOCAL * sx, 0.0, KITTI_CENTRE[0] * sx], [0.0, KITTI_FOCAL * sy, KITTI_CENTRE[1] * sy],
                     [0.0, 0.0, 1.0]])


def lidar_to_camera(frames_back: float = 0.0, ego_speed: float = 0.0) -> np.ndarray:
    """(4, 4) from the current LiDAR frame to the camera of the frame ``frames_back`` frames earlier (the ego drives
    straight along x at ``ego_speed`` metres per frame, so that camera stood ``frames_back * ego_speed`` behind)."""
    centre = CAMERA_IN_LIDAR - np.array([frames_back * ego_speed, 0.0, 0.0])
    out = np.eye(4)
    out[:3, :3] = LIDAR_TO_CAMERA_AXES
    out[:3, 3] = -LIDAR_TO_CAMERA_AXES @ centre
    return out


def frame_offsets(p: CameraParams) -> tuple[int, ...]:
    """The frames of a sample's images: 0 (current) first, then ``-k`` for each earlier frame."""
    return (0, *(-k for k in p.previous))


def rig(p: CameraParams, ego_speed: float) -> Camera:
    """The camera as :class:`~distilkit.data.info.DataInfo` describes it (current frame's calibration)."""
    k, t = intrinsics(p), lidar_to_camera(0.0, ego_speed)
    return Camera("cam2", tuple(map(tuple, k.tolist())), tuple(map(tuple, t.tolist())), (p.height, p.width),
                  frame_offsets(p))


def add_camera(batch: Batch, samples: list[dict[str, Any]]) -> Batch:
    """The batch with the samples' camera fields (when they have them): images as float 0..1, calibration, depth."""
    if not samples or "image" not in samples[0]:
        return batch
    import torch

    def stack(key: str, dtype: torch.dtype) -> torch.Tensor:
        return torch.stack([torch.from_numpy(np.ascontiguousarray(s[key])) for s in samples]).to(dtype)

    image = stack("image", torch.float32).div_(255.0).permute(0, 1, 4, 2, 3).contiguous()  # (B,T,H,W,3) -> (B,T,3,H,W)
    inputs = {**batch.inputs, "image": image, "intrinsics": stack("intrinsics", torch.float32),
              "lidar_to_camera": stack("lidar_to_camera", torch.float32)}
    return Batch(inputs, {**batch.targets, "depth": stack("depth", torch.float32)}, batch.meta)


__all__ = ["CAMERA_FIELDS", "CAMERA_INPUTS", "CAMERA_TARGETS", "add_camera", "frame_offsets", "intrinsics",
           "lidar_to_camera", "rig"]
