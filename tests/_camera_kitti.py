"""One exported SemanticKITTI folder with camera images per test process (conftest's
:func:`export_kitti`, 24 x 80 images), read by the paper-network tests of several modules and by the folder tests of
test_export_kitti, test_new_user_faults and test_cli_recipe (the images add image_2/ and the intrinsics in calib.txt;
scans, labels, voxels and poses are a plain export's); a test that adds files works on a copy
(:func:`camera_kitti_copy`)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from conftest import export_kitti

_FOLDERS: dict[str, Path] = {}


def camera_kitti(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder, exported on the first call of this process's session (read only: never write into it)."""
    key = str(tmp_path_factory.getbasetemp())
    if key not in _FOLDERS:
        _FOLDERS[key] = export_kitti(tmp_path_factory.mktemp("c_kitti"), "--camera", "camera={height: 24, width: 80}")
    return _FOLDERS[key]


def camera_kitti_copy(tmp_path_factory: pytest.TempPathFactory, name: str) -> Path:
    """A copy of the folder to add files to."""
    return Path(shutil.copytree(camera_kitti(tmp_path_factory), tmp_path_factory.mktemp(name) / "kitti"))
