"""Run reports (report.md, loss / per-class / bird's-eye plots), `distilkit report` and `distilkit compare`."""

from __future__ import annotations

import json
from contextlib import contextmanager
from typing import Iterator

import numpy as np
import pytest
import torch

from conftest import tiny_recipe
from distilkit.cli import main
from distilkit.engine.train.pipeline import Pipeline
from distilkit.metrics.bev import top_class
from distilkit.recipe import recipe_from_dict

pytestmark = pytest.mark.plots  # these tests look at the rendered pictures


@contextmanager
def unrendered() -> Iterator[None]:
    """Pictures drawn without rendering (tests/conftest.py's stand-in: every report path runs, up to the drawing)
    for what no test looks at, in these tests that otherwise render."""
    import conftest

    renders, conftest._RENDERS[0] = conftest._RENDERS[0], False
    try:
        yield
    finally:
        conftest._RENDERS[0] = renders


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory):
    """A teacher and its student. The teacher's pictures, which no test looks at (it is compared by its summary),
    are drawn without rendering; the student's and the recipe's are rendered by the run itself."""
    out = tmp_path_factory.mktemp("runs")
    with unrendered():
        Pipeline(recipe_from_dict(tiny_recipe(steps=2)), out, quiet=True).run(only=["teacher"])
    teacher, student = Pipeline(recipe_from_dict(tiny_recipe(steps=2)), out, quiet=True).run()
    assert teacher.reused and not student.reused
    return teacher.run_dir, student.run_dir


def naive_top_class(labels: np.ndarray, ignore: int) -> np.ndarray:
    out = np.full(labels.shape[:2], -1)
    for x in range(labels.shape[0]):
        for y in range(labels.shape[1]):
            for z in range(labels.shape[2]):  # the last occupied voxel going up wins
                if labels[x, y, z] not in (0, ignore):
                    out[x, y] = labels[x, y, z]
    return out


def test_top_class_against_a_loop() -> None:
    labels = torch.randint(0, 5, (6, 5, 4))
    labels[labels == 4] = 255
    labels[0, 0] = 0  # an empty column
    assert np.array_equal(top_class(labels, 255), naive_top_class(labels.numpy(), 255))
    assert top_class(labels, 255)[0, 0] == -1


def test_every_run_writes_its_report_with_plots_and_a_preview(runs) -> None:
    _, student = runs
    for name in ("report.md", "loss.png", "classes.png", "bev.png", "preview.npz"):
        assert (student / name).stat().st_size > 0, name
    summary = json.loads((student / "summary.json").read_text())
    with np.load(student / "preview.npz", allow_pickle=False) as z:
        grid = z["prediction"].shape
        assert z["prediction"].dtype.kind == "i" and z["target"].shape == grid and z["input"].shape[1] == 3
        assert list(z["class_names"]) == summary["classes"]["names"]
    text = (student / "report.md").read_text()
    assert f"| mIoU | {100 * summary['test']['best']['miou']:.2f} |" in text and "![" in text
    assert "| car |" in text and "dskd×10" in text


def test_report_command_rerenders_from_the_run_folder(runs, capsys) -> None:
    _, student = runs
    before = (student / "report.md").read_text()
    (student / "report.md").unlink()
    (student / "bev.png").unlink()
    assert main(["report", str(student)]) == 0
    assert (student / "report.md").read_text() == before and (student / "bev.png").is_file()
    with unrendered():  # what is looked at here: which reports it writes (the pictures: rendered just above)
        assert main(["report", str(student.parent)]) == 0  # every run under a recipe's folder
    assert str(student / "report.md") in capsys.readouterr().out


def test_report_of_a_folder_that_is_not_a_run_is_a_clear_error(tmp_path, capsys) -> None:
    assert main(["report", str(tmp_path)]) == 2
    assert "no finished stage run here" in capsys.readouterr().err
    (tmp_path / "summary.json").write_text("{not json")
    assert main(["compare", str(tmp_path), str(tmp_path)]) == 2
    assert "summary.json: unreadable" in capsys.readouterr().err


def test_compare_puts_two_runs_side_by_side(runs, tmp_path) -> None:
    teacher, student = runs
    assert main(["compare", str(teacher), str(student), "--out", str(tmp_path)]) == 0
    text = (tmp_path / "compare.md").read_text()
    st, ss = (json.loads((d / "summary.json").read_text())["test"]["best"] for d in (teacher, student))
    assert f"| mIoU best | {100 * st['miou']:.2f} | {100 * ss['miou']:.2f} | {100 * (ss['miou'] - st['miou']):+.2f} |" in text
    assert "| model.params.frames | 2 | 1 |" in text  # the configuration that differs
    assert (tmp_path / "compare.png").stat().st_size > 0


def test_point_cloud_preview_shows_scan_completion_and_scene() -> None:
    from distilkit.data.batch import Batch
    from distilkit.data.info import DataInfo
    from distilkit.metrics.registered import SceneCompletionScore
    from distilkit.taps import PointCloud

    scene = torch.randn(1, 50, 3) * 10
    batch = Batch({"scan": scene[:, :20], "scan_lengths": torch.tensor([12])},
                  {"scene_eval": scene, "scene_eval_lengths": torch.tensor([40])}, {"size": 1})
    pred = PointCloud.from_list([scene[0, :30] + 0.1])
    view = SceneCompletionScore.preview(pred, batch, DataInfo(grid=None))
    assert view["input"].shape == (12, 3) and view["target"].shape == (40, 3) and view["prediction"].shape == (30, 3)
    low = scene[0, :40, :2].min(dim=0).values.numpy() - 2
    assert view["extent"][[0, 2]] == pytest.approx(low, abs=1e-5)
