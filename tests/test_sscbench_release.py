"""SSCBench-KITTI-360 as the release ships it (issue 57, items 7, 8 and 14): frames listed from ``voxels/*.bin`` as
the benchmark's loader lists them (label-only frames left out and counted), its frame counts stated with their
sources, label ids outside the learning map named by ``validate``, and the roles' drives checked as a recipe gives
them."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from pydantic import ValidationError

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from _sscbench import DRIVE, SHAPE, scene, write_folder
from conftest import ROOT, folder_recipe
from distilkit.cli import main
from distilkit.data.sscbench import SscbenchParams
from distilkit.data.sscbench_folder import SscbenchDataset, sscbench_check
from distilkit.errors import DataError

D03 = DRIVE.format(3)
LABEL_ONLY = ("000970", "000975", "000980", "000985")  # the release's drive 0003 (ai4ce/SSCBench issue #23)


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    """Drive 0003 as the release has it: frames with every file, and preprocess/labels/ frames with no voxels/."""
    root = tmp_path_factory.mktemp("release") / "KITTI-360"
    frames = write_folder(root, {3: ("000000", "000005"), 6: ("000000",)}, images=False)
    labels = root / "preprocess" / "labels" / D03
    for frame in LABEL_ONLY:
        np.save(labels / f"{frame}_1_1.npy", np.zeros(SHAPE, np.float32))
        np.save(labels / f"{frame}_1_8.npy", np.zeros((32, 32, 4), np.float32))
    return root, frames


def _said(capsys) -> str:
    said = capsys.readouterr()
    return " ".join((said.out + said.err).split())


def _recipe(tmp_path, root, dataset: str = "sscbench-kitti360", **data):
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(folder_recipe(root, dataset=dataset, scale=8, **data)))
    return path


def test_frames_come_from_the_voxel_inputs_and_label_only_frames_are_left_out_and_counted(release, tmp_path) -> None:
    root, _ = release
    ds = SscbenchDataset(SscbenchParams(root=str(root), train=["03"], targets="preprocess"), "train")
    assert [frame for _, frame in ds.items] == ["000000", "000005"]
    (note,) = ds.notes
    assert "4 frames" in note and "000970" in note and "000985" in note and "voxels/*.bin" in note
    other = tmp_path / "KITTI-360"  # with voxels/ targets, a .label with no .bin beside it is left out the same way
    write_folder(other, {3: ("000000", "000005")}, images=False)
    (other / "data_2d_raw" / D03 / "voxels" / "000000.bin").unlink()
    ds = SscbenchDataset(SscbenchParams(root=str(other), train=["03"]), "train")
    assert [frame for _, frame in ds.items] == ["000005"] and "1 frame" in ds.notes[0] and "000000" in ds.notes[0]


def test_validate_passes_on_the_release_layout(release) -> None:
    root, _ = release
    assert sscbench_check(SscbenchParams(root=str(root), train=["03"], targets="preprocess"), "train") is None


def test_validate_says_which_frames_it_leaves_out(release, tmp_path, capsys) -> None:
    from distilkit.cli import main

    root, _ = release
    path = _recipe(tmp_path, root, train=["03"], val=None, test=None, targets="preprocess")
    assert main(["validate", str(path), "--static"]) == 0
    said = _said(capsys)
    assert f"note: data_2d_raw/{D03}: 4 frames with a target but no voxels/*.bin input left out" in said
    assert "000970" in said and "000985" in said


def test_the_frame_counts_are_the_releases_with_the_readmes_beside_them() -> None:
    from distilkit.data import sscbench

    assert sscbench.RELEASE_FRAMES == {"train": 8483, "test": 2165}
    assert sscbench.README_FRAMES == {"train": 8487, "valid": 1812, "test": 2566}
    for doc in (ROOT / "docs" / "reference" / "datasets.md", ROOT / "docs" / "how-to" / "real-data.md"):
        text = doc.read_text()
        assert "8,483" in text and "2,165" in text and "issue #23" in text, doc


def test_a_drive_twice_or_a_validation_drive_trained_on_is_refused(release) -> None:
    root, _ = release
    with pytest.raises(ValidationError, match="2013_05_28_drive_0000_sync given twice"):
        SscbenchParams(root=str(root), train=["00", "0000"])
    with pytest.raises(ValidationError, match="val: 2013_05_28_drive_0006_sync is also a training drive"):
        SscbenchParams(root=str(root), train=["00", "06"], val=["06"])
    with pytest.raises(ValidationError, match="val: 2013_05_28_drive_0000_sync is also a training drive"):
        SscbenchParams(root=str(root), val=["0"])  # the official train split holds drive 0000
    SscbenchParams(root=str(root), train=["00", "06"], val=None)  # a final model on train + valid


@pytest.mark.parametrize("dataset", ["sscbench-kitti360", "semantickitti"])
def test_an_empty_or_unquoted_train_list_gets_its_own_line(release, tmp_path, capsys, dataset) -> None:
    root, _ = release
    assert main(["validate", str(_recipe(tmp_path, root, dataset, train=[])), "--static"]) == 2
    said = _said(capsys)
    assert "train: none given" in said and "not a complete" not in said
    assert main(["validate", str(_recipe(tmp_path, root, dataset, train=[0])), "--static"]) == 2
    said = _said(capsys)
    assert "quote" in said and "Input should be" not in said and "literal" not in said


KITTI360_OWN = {7: 7, 9: 8, 11: 11, 13: 21, 14: 22, 1: 26, 4: 27, 6: 24, 15: 17, 16: 20}  # train id -> KITTI-360's id


def test_validate_names_a_drive_labelled_with_ids_the_learning_map_lacks(tmp_path, capsys) -> None:
    root = tmp_path / "KITTI-360"
    write_folder(root, {0: ("000000",), 6: ("000000",)}, images=False)
    truth = scene(0).truth
    own = np.zeros(SHAPE, np.uint16)
    for train_id, kitti360_id in KITTI360_OWN.items():  # labelled with KITTI-360's own ids (car 26, road 7, ...)
        own[truth == train_id] = kitti360_id
    own[(truth > 0) & (truth != 255) & (own == 0)] = 41  # box
    label = root / "data_2d_raw" / DRIVE.format(0) / "voxels" / "000000.label"
    own.astype("<u2").tofile(label)
    assert main(["validate", str(_recipe(tmp_path, root, train=["00"], val=["06"], test=None)), "--static"]) == 2
    said = _said(capsys)
    assert f"data_2d_raw/{DRIVE.format(0)}/voxels/000000.label" in said and "learning map" in said
    assert "KITTI-360's own ids" in said


def test_a_raw_id_beyond_the_table_names_the_file_and_the_dataset(tmp_path) -> None:
    root = tmp_path / "KITTI-360"
    write_folder(root, {6: ("000000",)}, images=False)
    label = root / "data_2d_raw" / DRIVE.format(6) / "voxels" / "000000.label"
    raw = np.fromfile(label, "<u2")
    raw[123] = 400
    raw.tofile(label)
    ds = SscbenchDataset(SscbenchParams(root=str(root), train=["06"], val=None), "train")
    with pytest.raises(DataError) as err:
        ds[0]
    assert str(label) in str(err.value) and "SSCBench-KITTI-360" in str(err.value)
    assert "SemanticKITTI" not in str(err.value) and "400" in str(err.value)
