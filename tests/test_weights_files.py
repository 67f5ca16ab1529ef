"""What is not a checkpoint, given where one is read (a weights file, a run folder, a recipe's ``checkpoint:``), is
named in one line by what it is — a text file, a NumPy file, a folder (and what a folder was expected to hold) —
never torch's unpickler's words ("KeyError: 101", "Unsupported operand 147") or "no such file" for a folder."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from distilkit.cli import main
from distilkit.engine.assemble.checks import fit_problem
from distilkit.engine.assemble.runs import checkpoint_path
from distilkit.errors import DataError
from distilkit.weights import load_checkpoint, read_state_dict


def message(read, path: Path) -> str:
    with pytest.raises(DataError) as err:
        read(path)
    text = str(err.value)
    assert "\n" not in text, text
    return text


def test_a_text_or_numpy_file_is_named_for_what_it_is(tmp_path: Path) -> None:
    text = tmp_path / "notes.txt"
    text.write_text("hello, world\nsecond line\n")
    array = tmp_path / "scan.npy"
    np.save(array, np.zeros((5, 3), np.float32))
    archive = tmp_path / "frames.npz"
    np.savez(archive, points=np.zeros(3), labels=np.zeros(2))
    for read in (load_checkpoint, read_state_dict):
        assert message(read, text) == (f"{text}: not a readable checkpoint: it is a text file (first line: 'hello, "
                                       "world'), not a file torch.save wrote")
        assert message(read, array) == (f"{array}: not a readable checkpoint: it is a NumPy array file (.npy: "
                                        "float32, shape (5, 3)), not a file torch.save wrote")
        assert message(read, archive) == (f"{archive}: not a readable checkpoint: it is a NumPy archive (.npz: "
                                          "points, labels), not a file torch.save wrote")


def test_a_folder_given_as_a_checkpoint_file_says_what_it_holds(tmp_path: Path) -> None:
    run = tmp_path / "teacher-1a"
    (run / "checkpoints").mkdir(parents=True)
    for name in ("best.pt", "last.pt"):
        (run / "checkpoints" / name).write_bytes(b"")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert message(load_checkpoint, run) == (f"{run}: not a readable checkpoint: it is a folder, not a file; it holds "
                                             "checkpoints/best.pt, checkpoints/last.pt: give one of them")
    assert message(read_state_dict, empty) == (f"{empty}: not a readable checkpoint: it is a folder, not a file; it "
                                               "holds no checkpoint file (.pt, .pth, .ckpt) and no stage run")
    assert message(load_checkpoint, tmp_path / "gone.pt") == f"{tmp_path / 'gone.pt'}: no such file"
    # validate's check of a recipe's `checkpoint:` (init, teacher) says the same, not "no such file"
    assert fit_problem(run, None, None, True) == message(load_checkpoint, run)


def test_a_folder_given_as_a_run_says_what_a_run_folder_holds(tmp_path: Path, capsys) -> None:
    recipe = tmp_path / "runs" / "tiny"
    for stage in ("teacher-1a", "student-2b"):
        (recipe / stage / "checkpoints").mkdir(parents=True)
        (recipe / stage / "checkpoints" / "last.pt").write_bytes(b"")
    expected = "no checkpoints/best.pt in it (a stage's run folder runs/<recipe>/<stage>-<hash> holds it)"
    assert message(checkpoint_path, recipe) == (f"{recipe}: not a stage's run folder: {expected}; it holds stage runs: "
                                                "student-2b, teacher-1a: give one of them")
    only_last = recipe / "teacher-1a"  # a run folder without its best checkpoint
    assert message(checkpoint_path, only_last) == (f"{only_last}: no checkpoints/best.pt in this stage's run folder; "
                                                   "it holds checkpoints/last.pt: give that file")
    assert main(["export", str(recipe), "--out", str(tmp_path / "student.pt")]) == 2  # a command taking a run
    assert capsys.readouterr().err.strip() == f"error: {message(checkpoint_path, recipe)}"
