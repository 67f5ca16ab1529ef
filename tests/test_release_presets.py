"""A recipe or sweep that says it has a release's (or the authors') settings has them: each claim is a row of
:data:`CLAIMS` — file, variant or stage, and the settings with their release values — read from the *resolved*
recipe (:func:`~distilkit.engine.store.identity.stage_hashes`: the record a run writes as ``recipe.resolved.yaml``,
defaults filled in), and every file under recipes/ whose comments make such a claim has a row."""

from __future__ import annotations

import re
from functools import lru_cache
from typing import Any

import pytest

from conftest import ROOT
from distilkit.engine.assemble.resolve import resolve
from distilkit.engine.store.identity import stage_hashes
from distilkit.recipe import load_recipe
from distilkit.sweep.spec import load_sweep

HASSC_AS_RELEASED = {  # songw-zju/HASSC at 20097ee: detectors/hassc_voxformer.py, utils/*, hassc-voxformer-T.py
    "teacher.mode": "train", "teacher.ema.mode": "train", "teacher.ema.buffers": "copy_once",
    "teacher.ema.momentum": 0.99,
    "distill[hassc_kd].weight": 48.0, "distill[hassc_kd].params.dynamic_weight": True,
    "distill[hassc_kd].params.temperature": 1.0, "distill[hassc_kd].params.classes": "non_empty",
    "distill[hassc_kd].params.per": "sample",
    "distill[hassc_hvm].weight": 1.0, "distill[hassc_hvm].params.rank": "logits",
    "distill[hassc_hvm].params.class_weights": "release", "distill[hassc_hvm].params.points": 4096,
    "distill[hassc_hvm].params.oversample": 3, "distill[hassc_hvm].params.omega": 0.75,
    "distill[hassc_hvm].params.alpha": 0.2, "distill[hassc_hvm].params.beta": 1.0,
    "distill[hassc_hvm].params.delta": 0.1, "distill[hassc_hvm].params.reduce": "per_sample",
    "task_losses[hassc_ce].weight": 1.0, "task_losses[hassc_ce].params.class_weights": "release",
    "task_losses[geo_scal].weight": 1.0, "task_losses[sem_scal].weight": 1.0,
}
# distilkit's defaults in the HASSC row: the same objectives and weights; the header names what differs
HASSC_DEFAULTS = {
    "teacher.mode": "eval", "teacher.ema.buffers": "average", "distill[hassc_hvm].params.rank": "probabilities",
    "distill[hassc_hvm].params.class_weights": "log_frequency", "task_losses[hassc_ce].weight": 10.0,
    "task_losses[hassc_ce].params.class_weights": "log_frequency",
    **{k: HASSC_AS_RELEASED[k] for k in ("distill[hassc_kd].weight", "distill[hassc_hvm].weight",
                                         "distill[hassc_hvm].params.delta", "distill[hassc_hvm].params.alpha",
                                         "distill[hassc_hvm].params.beta", "teacher.ema.momentum")},
}
L2COCC_WEIGHTS = {"distill[l2cocc_pad].weight": 70.0, "distill[l2cocc_fsd].weight": 4.0,  # its configs
                  "distill[l2cocc_relation].weight": 5.0, "distill[l2cocc_pad].params.include_empty": False,
                  "distill[l2cocc_fsd].params.reduce": "per_sample"}
SCRIBBLE2SCENE_CE = {"task_losses[weighted_ce].weight": 10.0, "task_losses[weighted_ce].params.normalize": "valid",
                     "task_losses[geo_scal].weight": 1.0}
DPO_RELEASE = {"optimizer.name": "sgd", "optimizer.lr": 1e-5, "train.grad_clip": 0.05,
               "distill[distillation_dpo].params.aux_lr": 1e-5, "distill[distillation_dpo].params.aux_optimizer": "sgd",
               "distill[distillation_dpo].params.aux_grad_clip": 0.05, "distill[distillation_dpo].params.sign": "release",
               "distill[distillation_dpo].params.beta": None}
SCRIBBLE2SCENE_SCHEDULE = {"optimizer.name": "adamw", "optimizer.lr": 2e-4, "optimizer.weight_decay": 0.01,
                           "optimizer.schedule.name": "cosine", "optimizer.schedule.warmup_steps": 500,
                           "train.grad_clip": 35.0, "train.batch_size": 1, "train.epochs": 20}

# (file under recipes/, variant of a sweep or stage of a recipe, {setting: the release's value})
CLAIMS: list[tuple[str, str, dict[str, Any]]] = [
    ("sweeps/hassc.yaml", "hassc_release", HASSC_AS_RELEASED),
    ("sweeps/hassc.yaml", "hassc", HASSC_DEFAULTS),
    ("sweeps/l2cocc.yaml", "l2cocc", {**L2COCC_WEIGHTS, "teacher.mode": "train"}),
    ("sweeps/l2cocc.yaml", "l2cocc_eval", {**L2COCC_WEIGHTS, "teacher.mode": "eval"}),
    ("sweeps/l2cocc.yaml", "pad", {"distill[l2cocc_pad].weight": 70.0, "teacher.mode": "train"}),
    ("sweeps/l2cocc.yaml", "pad_fsd", {"distill[l2cocc_pad].weight": 70.0, "distill[l2cocc_fsd].weight": 4.0,
                                       "teacher.mode": "train"}),
    ("sweeps/l2cocc.yaml", "monoocc_raw", {"distill[monoocc_kl].weight": 2.0,
                                           "distill[monoocc_kl].params.form": "raw"}),
    ("sweeps/l2cocc.yaml", "monoocc", {"distill[monoocc_kl].weight": 2.0, "distill[monoocc_kl].params.form": "softmax"}),
    ("sweeps/quickstart_methods.yaml", "licrocc_kl_10", {"distill[licrocc_kl].weight": 10.0}),
    ("sweeps/quickstart_methods_stored.yaml", "licrocc_kl_10", {"distill[licrocc_kl].weight": 10.0}),
    ("sweeps/quickstart_methods_stored.yaml", "bev_2", {"distill[bev_from_voxels].weight": 2.0}),
    ("sweeps/quickstart_methods.yaml", "licrocc_bev_4", {"distill[licrocc_bev].weight": 4.0}),
    ("sweeps/quickstart_methods.yaml", "licrocc_brd_40", {"distill[licrocc_affinity].weight": 40.0,
                                                          "distill[licrocc_affinity].params.size": [32, 32]}),
    ("sweeps/quickstart_methods.yaml", "bev_2", {"distill[bev_from_voxels].weight": 2.0,
                                                 "distill[bev_from_voxels].params.adapter": "release"}),
    ("scribble2scene.yaml", "student", SCRIBBLE2SCENE_CE),
    ("scorelidar.yaml", "dpo", DPO_RELEASE),
    ("scpnet_dskd.yaml", "teacher", {"data.params.input_frames": 5, "model.params.frames": 5}),
    ("semantickitti_scpnet.yaml", "teacher", {"data.params.input_frames": 5, "model.params.frames": 5}),
    ("paper/scribble2scene.yaml", "student", {**SCRIBBLE2SCENE_SCHEDULE, **SCRIBBLE2SCENE_CE,
                                              "model.params.size": "paper"}),
    ("paper/scpnet.yaml", "teacher", {"model.params.size": "paper", "model.params.frames": 5,
                                      "data.params.input_frames": 5}),
    ("paper/js3cnet.yaml", "teacher", {"model.params.size": "paper"}),
    ("paper/scorelidar.yaml", "teacher", {"model.params.size": "paper"}),
]

CLAIM = re.compile(r"\brelease'?s?\b|\bas released\b|\bauthors'", re.IGNORECASE)


@lru_cache(maxsize=None)
def resolved(file: str, name: str) -> dict[str, Any]:
    """The resolved record of a sweep's variant or a recipe's stage."""
    path = ROOT / "recipes" / file
    recipe = load_sweep(path).recipes[name] if file.startswith("sweeps/") else load_recipe(path)
    _, configs = stage_hashes(resolve(recipe, str(path)))
    return configs[name]


def lookup(record: dict[str, Any], path: str) -> Any:
    """``a.b[name].c``: keys, and ``[name]`` the one item of a list whose ``name`` it is."""
    value: Any = record
    for part in path.split("."):
        key, _, item = part.partition("[")
        value = value[key]
        if item:
            found = [t for t in value if t["name"] == item.rstrip("]")]
            assert len(found) == 1, f"{path}: {len(found)} terms named {item.rstrip(']')}"
            value = found[0]
    return value


@pytest.mark.parametrize("file,name,settings", CLAIMS, ids=[f"{f}:{n}" for f, n, _ in CLAIMS])
def test_the_resolved_recipe_has_the_settings_it_claims(file: str, name: str, settings: dict[str, Any]) -> None:
    record = resolved(file, name)
    wrong = {path: (lookup(record, path), want) for path, want in settings.items() if lookup(record, path) != want}
    assert not wrong, f"recipes/{file} {name}: (resolved, claimed) {wrong}"


def test_every_recipe_that_claims_a_release_setting_is_checked() -> None:
    claiming = {str(p.relative_to(ROOT / "recipes")) for p in (ROOT / "recipes").rglob("*.yaml")
                if any(CLAIM.search(line) for line in p.read_text(encoding="utf-8").splitlines()
                       if line.lstrip().startswith("#") or "label:" in line)}
    assert claiming, "the pattern finds the claims"
    assert claiming <= {f for f, _, _ in CLAIMS}, f"claims with no row in CLAIMS: {sorted(claiming - {f for f, _, _ in CLAIMS})}"


def test_the_hassc_rows_differ_in_exactly_the_choices_the_header_names() -> None:
    """The sweep's two HASSC rows are the same method: they differ in the release's choices and nothing else
    (labels aside, and the code versions of the terms they run)."""
    a, b = resolved("sweeps/hassc.yaml", "hassc_release"), resolved("sweeps/hassc.yaml", "hassc")
    differ = {k for k in set(a) | set(b) if a.get(k) != b.get(k)} - {"label", "versions"}  # versions: of sem_scal
    assert differ == {"teacher", "task_losses", "distill"}
    assert [t["name"] for t in a["distill"]] == [t["name"] for t in b["distill"]] == ["hassc_kd", "hassc_hvm"]
    assert [t["name"] for t in a["task_losses"]] == ["hassc_ce", "geo_scal", "sem_scal"]
    assert [t["name"] for t in b["task_losses"]] == ["hassc_ce", "geo_scal"]
