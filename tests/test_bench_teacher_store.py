"""``distilkit bench teacher-store``: run through ``run_bench`` (the CLI's entry) at the tests' sizes with the
``size: tiny`` stand-ins (``teacher_store_cases(..., test=True)``), it has a forward row and a row for each layout of
each paper recipe whose distillation reads teacher taps, and ScoreLiDAR's (whose VSD calls the teacher) as a line
with its reason; the exact layout reads back the live teacher's bits, float16 halves the bytes, top-k shrinks the
logits' store, and every time is positive."""

from __future__ import annotations

import functools
from typing import Iterator

import pytest
import torch

from distilkit.bench import store_compare
from distilkit.bench import teacher_store as bench_store

FAMILIES = ("SCPNet", "JS3C-Net", "VoxFormer")


@pytest.fixture(scope="module")
def ran() -> Iterator[tuple[dict[str, dict], str]]:
    """The bench's rows by objective and its printed output, run once for this module's tests on the CPU."""
    import contextlib
    import io

    from distilkit.bench import BENCHES, run_bench

    saved = BENCHES["teacher-store"]
    BENCHES["teacher-store"] = functools.partial(bench_store.teacher_store_cases, test=True)
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            rows = run_bench(["teacher-store"], device="cpu")
    finally:
        BENCHES["teacher-store"] = saved
        bench_store.release()
    yield {row["objective"]: row for row in rows}, " ".join(out.getvalue().split())


def test_every_family_has_a_forward_row_and_a_row_for_each_layout(ran) -> None:
    rows, out = ran
    expected = {f"teacher-store: {f} {what}" for f in FAMILIES for what in ("forward", *bench_store.LAYOUTS)}
    assert set(rows) == expected
    for family in FAMILIES:
        forward = rows[f"teacher-store: {family} forward"]
        assert forward["fast_ms"] > 0 and "size tiny, batch 1" in forward["size"]
        for layout in bench_store.LAYOUTS:
            row = rows[f"teacher-store: {family} {layout}"]
            columns = row["columns"]
            assert row["fast_ms"] > 0 and float(columns["1st read ms"].replace(",", "")) > 0
            assert columns["bytes/sample"].endswith(("MiB", "KiB")) and columns["validate"] in ("accepts", "refuses")
            assert columns["fwd/read"].endswith("×")
    assert "teacher-store: LiDiff (scorelidar student): skipped — " in out
    assert "(vsd) calls the teacher's predict_noise()" in out


def test_the_layouts_figures(ran) -> None:
    """float32 reads back the live teacher exactly; float16 stores fewer bytes; top-k stores fewer where a logits
    tap is stored; masked layouts compare inside the mask; the notes say so."""
    rows, out = ran
    cases = {c.objective: c for c in bench_store.teacher_store_cases(torch.device("cpu"), True, test=True)}
    assert "LiDiff" not in " ".join(o for o, c in cases.items() if c.skipped is None)
    for family in FAMILIES:
        exact = rows[f"teacher-store: {family} float32"]
        assert exact["value"] == 0.0 and exact["columns"]["vs float32"] == "1.00×"
        assert all(part.endswith(" 0") for part in exact["columns"]["max |Δ|"].split("; "))
        # every distillation term of the stage, computed with the read-back outputs: the same value for float32
        terms = exact["columns"]["terms |Δ| (rel.)"].split("; ")
        assert terms and all(part.endswith(" 0") for part in terms), terms
        assert {part.split()[0] for part in terms} == ({"rgo2d"} if family == "VoxFormer" else {"dskd"})
        half = rows[f"teacher-store: {family} float16"]
        assert 0 < half["value"] < 0.1 and _mib(half) < _mib(exact)
        rel = [float(part.split("(")[1].rstrip(")")) for part in half["columns"]["terms |Δ| (rel.)"].split("; ")
               if "(" in part]
        assert all(r < 1e-2 for r in rel), half["columns"]["terms |Δ| (rel.)"]
        if family == "VoxFormer":  # its logits (voxel_logits) take the top-k and the masked layouts
            for k in ("topk 2", "topk 4", "voxels valid", "voxels occupied"):
                assert _mib(rows[f"teacher-store: {family} {k}"]) < _mib(exact), k
            assert _mib(rows[f"teacher-store: {family} voxels occupied"]) < \
                _mib(rows[f"teacher-store: {family} voxels valid"])
            assert rows[f"teacher-store: {family} topk 2"]["columns"]["validate"] == "refuses"  # rgo2d reads scores
            # RGO²D reads the occupied voxels' scores: the occupied store gives its value exactly, top-k does not
            assert rows[f"teacher-store: {family} voxels occupied"]["columns"]["terms |Δ| (rel.)"] == "rgo2d 0"
            assert rows[f"teacher-store: {family} topk 2"]["columns"]["terms |Δ| (rel.)"] != "rgo2d 0"
            assert "VoxFormer voxels valid: max |Δ| of logits inside the mask only" in out
            assert "max |Δ| of logits: of the softmax probabilities" in out
        else:  # the sparse completion: stored whole by every layout but the precisions
            assert "completion stored whole: the layout does not apply to it" in out
    assert "8 draws of train.augment" in out  # JS3C-Net's flips and quarter turns


def test_a_masked_layouts_difference_is_inside_its_mask() -> None:
    """:func:`difference` compares a masked tap inside the mask only and a top-k tap's softmax."""
    live = torch.randn(1, 3, 2, 2, 1)
    read = live.clone()
    mask = torch.zeros(2, 2, 1, dtype=torch.bool)
    mask[0, 0, 0] = True
    read[0, :, 1, 1, 0] = 0  # outside the mask: as a masked store reads it back
    assert store_compare.difference(live, read, {"masked": True}, mask) == 0.0
    assert store_compare.difference(live, read, {}, None) > 0
    assert store_compare.difference(live, live + 5.0, {"topk": 2}, None) == pytest.approx(0.0, abs=1e-6)


def _mib(row: dict) -> float:
    number, unit = row["columns"]["bytes/sample"].split()
    return float(number.replace(",", "")) / (1024 if unit == "KiB" else 1)
