"""`distilkit compare` of two runs whose datasets have different class tables (a SemanticKITTI run against an
SSCBench-KITTI-360 run): per-class rows matched by the class's name, never by its position, and the classes one run
lacks said in compare.md and on the console."""

from __future__ import annotations

import json
from pathlib import Path

from distilkit.cli import main
from distilkit.data.classes import CLASS_COLOURS, CLASS_NAMES
from distilkit.data.sscbench import NAMES as SSCBENCH_NAMES


def fake_run(folder: Path, names: list[str], iou: dict[str, float]) -> Path:
    """A finished SSC stage run's folder with only its summary: ``iou`` per class name (classes 1..K-1)."""
    folder.mkdir(parents=True)
    scores = {"miou": 0.5, "iou": 0.6, "precision": 0.7, "recall": 0.8, "class_iou": [iou[n] for n in names[1:]]}
    summary = {"stage": folder.name, "adapter": "scpnet", "metric": {"name": "ssc", "key": "miou"},
               "classes": {"names": names, "colours": [list(CLASS_COLOURS[0])] * len(names)},
               "steps": 2, "best": {"step": 2, "scores": scores}, "last": scores, "report_split": "test",
               "test": {"best": scores, "last": scores, "best_step": 2}}
    (folder / "summary.json").write_text(json.dumps(summary))
    return folder


def test_compare_matches_classes_by_name_and_names_those_one_run_lacks(tmp_path, capsys) -> None:
    kitti = list(CLASS_NAMES)
    kitti360 = list(SSCBENCH_NAMES)
    # each class's IoU is its position in its own table / 100: a row read by position shows another class's value
    a = fake_run(tmp_path / "kitti", kitti, {n: i / 100 for i, n in enumerate(kitti)})
    b = fake_run(tmp_path / "kitti360", kitti360, {n: i / 100 for i, n in enumerate(kitti360)})
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "out")]) == 0
    text = (tmp_path / "out" / "compare.md").read_text()
    for name in ("road", "sidewalk", "building", "pole"):  # in both tables, at different positions
        ia, ib = kitti.index(name), kitti360.index(name)
        assert f"| {name} | {ia:.1f} | {ib:.1f} | {ib - ia:+.1f} |" in text, name
    for name in ("bicyclist", "motorcyclist", "trunk"):  # SemanticKITTI's only
        assert f"| {name} | {kitti.index(name):.1f} | — | — |" in text, name
    for name in ("other-structure", "other-object"):  # SSCBench-KITTI-360's only
        assert f"| {name} | — | {kitti360.index(name):.1f} | — |" in text, name
    said = "B lacks 3 of A's classes: bicyclist, motorcyclist, trunk; A lacks 2 of B's: other-structure, other-object"
    assert said in text
    assert said in " ".join(capsys.readouterr().out.split())  # on the console too, however it is wrapped
