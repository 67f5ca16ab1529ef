"""Scenes and seeds (issue 59, item 5): an interval that resamples the test scenes as well as the training seeds.

The table's interval is Student's t over the seeds: it takes each seed's score on the fixed test scenes as exact,
so it speaks of training noise alone. The test scenes are a sample too — correlated frames of few sequences — and
which scenes happened to be in the split moves a paired difference as well. Each run keeps its best checkpoint's
per-scene intersections and unions (``scene_counts.npz``, :meth:`distilkit.metrics.registered.SSCScore.per_scene`);
from them :func:`~distilkit.report.multiple.hierarchical_bootstrap` resamples seeds and scenes (crossed: one draw of
the scenes serves every seed of a replicate) and recomputes the paired mIoU difference as the official metric does
(every class, one absent from a draw scoring 0), 2000 replicates from ``numpy.random.default_rng(0)``, the
percentile interval. Only rows whose runs all kept their counts, on the same scenes as the baseline's, get one.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from distilkit.report.numbers import interval, signed

SCENE_COUNTS = "scene_counts.npz"
DRAWS = 2000


def read(run_dir: Path | None) -> dict[str, Any] | None:
    """A run's per-scene counts (None: the run kept none, or the file does not read as one)."""
    import numpy as np

    path = Path(run_dir) / SCENE_COUNTS if run_dir is not None else None
    if path is None or not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            out = {"ids": [str(i) for i in f["ids"]], "inter": f["inter"].astype(np.int64),
                   "union": f["union"].astype(np.int64), "split": str(f["split"])}
    except (OSError, ValueError, KeyError):
        return None
    ok = out["inter"].ndim == 2 and out["inter"].shape == out["union"].shape == (len(out["ids"]), out["inter"].shape[1])
    return out if ok else None


def annotate(rows: list[dict[str, Any]], baseline: str | None) -> None:
    """Set ``boot`` (``ci``, ``estimate``, ``scenes``) on each row with paired differences over two seeds at least to
    its reference (``row["reference"]``, else ``baseline``: the stage its Δ is taken to), where every paired seed of
    both kept its counts on the same scenes; the rows' ``scene_counts`` (per seed) come from :func:`read`."""
    import numpy as np

    from distilkit.report.multiple import hierarchical_bootstrap

    by_name = {r["stage"]: r for r in rows}
    for row in rows:
        row.pop("boot", None)
        base = by_name.get(row.get("reference") or baseline or "")
        if (base is None or row is base or len(row["delta"]) < 2 or not row.get("scene_counts")
                or not base.get("scene_counts") or row["view"].main[0] != "miou"):
            continue
        seeds = [s for s in row["seeds"] if s in base["seeds"]]
        mine, theirs = row["scene_counts"], base["scene_counts"]
        if any(s not in mine or s not in theirs or mine[s]["ids"] != theirs[s]["ids"] for s in seeds):
            continue
        ids = theirs[seeds[0]]["ids"]
        if any(theirs[s]["ids"] != ids for s in seeds):
            continue
        inter = {k: np.stack([c[s]["inter"] for s in seeds]) for k, c in (("m", mine), ("b", theirs))}
        union = {k: np.stack([c[s]["union"] for s in seeds]) for k, c in (("m", mine), ("b", theirs))}
        estimate, low, high = hierarchical_bootstrap(inter, union, "m", "b", draws=DRAWS, absent="zero")
        row["boot"] = {"ci": (low, high), "estimate": estimate, "scenes": len(ids)}


def markdown(rows: list[dict[str, Any]]) -> list[str]:
    """The section with each row's t-interval over seeds beside its interval over seeds and scenes, and which is
    wider (empty where no row has the latter)."""
    booted = [r for r in rows if "boot" in r]
    if not booted:
        return []
    scale = booted[0]["view"].main[2]

    wider = [r for r in booted if _width(r["boot"]["ci"]) > _width(r["delta_ci"])]
    scenes = booted[0]["boot"]["scenes"]
    lines = ["", "## Scenes and seeds", "",
             f"Each row's 95 % interval of Δ {booted[0]['view'].main[1]} two ways: Student's t over the seeds (the "
             f"table's: training noise alone, the {scenes} test scenes taken as fixed), and a bootstrap that "
             f"resamples the seeds and the {scenes} scenes together ({DRAWS} replicates, crossed: one draw of the "
             "scenes for every seed of a replicate, Owen 2007; mIoU recomputed from the drawn scenes' counts; "
             "percentile interval).", "",
             f"The bootstrap interval is the wider for {len(wider)} of the {len(booted)} rows. Where it is wider, the "
             "scenes' own sampling noise — which frames happened to be in the split — is larger than what the "
             "t quantile's allowance for few seeds adds: it speaks of new scenes as well as new seeds. Where it is "
             "narrower, the method's gain is much the same on every scene, and the bootstrap's percentile interval "
             f"over only {len(booted[0]['delta'])} seeds is too short (it resamples the seeds' own spread, without "
             "the t quantile's widening): read the wider of the two.", "",
             "| row | Δ | t over seeds | seeds × scenes (bootstrap) | wider |", "|---|---|---|---|---|"]
    for r in booted:
        lines.append(f"| {r['label']} | {signed(r['delta_mean'], scale)} | {interval(*r['delta_ci'], scale)} | "
                     f"{interval(*r['boot']['ci'], scale)} | {'bootstrap' if r in wider else 't'} |")
    return lines + [""]


def _width(ci: tuple[float, float]) -> float:
    return ci[1] - ci[0] if not math.isnan(ci[0]) else math.nan


__all__ = ["DRAWS", "SCENE_COUNTS", "annotate", "markdown", "read"]
