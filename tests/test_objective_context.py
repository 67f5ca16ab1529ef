"""Objectives that own models: an auxiliary network with its own optimizer, stepped in `update` with
the batch and detached taps, and a teacher capability (`denoise`) called through the context instead of
the teacher's eager outputs -- what ScoreLiDAR's VSD needs, with nothing special in the trainer."""

from __future__ import annotations

import json
from typing import Any, Iterator

import pytest
import torch
from pydantic import BaseModel, ConfigDict
from torch import Tensor, nn

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import tiny_recipe
from distilkit.data.batch import Batch
from distilkit.weights import load_checkpoint
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import RecipeError
from distilkit.objectives.base import MultiTapObjective, register_objective
from distilkit.recipe import recipe_from_dict
from distilkit.registry import ADAPTERS, OBJECTIVES
from distilkit_adapters.scpnet.adapter import SCPNetAdapter

CALLS = {"denoise": 0, "frozen_forward": 0}


class DenoisingSCPNet(SCPNetAdapter):
    """SCPNet with a stand-in teacher capability: ``denoise(x)`` (here: halve the logits)."""

    def forward(self, batch: Batch) -> dict[str, Any]:
        if not any(p.requires_grad for p in self.parameters()):  # only the frozen teacher
            CALLS["frozen_forward"] += 1
        return super().forward(batch)

    def denoise(self, x: Tensor) -> Tensor:
        CALLS["denoise"] += 1
        return 0.5 * x


class AuxParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    lr: float = 0.01
    inner_steps: int = 2


class AuxScore(MultiTapObjective):
    """Student logits pulled towards the teacher's denoised version through an auxiliary network that
    trains itself (own Adam, several steps per student step) on the detached student logits."""

    Params = AuxParams
    CONSUMES = {"student": "voxel_logits"}
    TEACHER_ROLES = frozenset()
    REQUIRES = frozenset({"denoise"})

    def setup(self, taps: dict[str, Any], batch: Batch) -> None:
        k = taps["student"].shape[1]
        self.aux = nn.Linear(k, k)

    def own_optimizer(self) -> torch.optim.Optimizer:
        self.opt = torch.optim.Adam(self.aux.parameters(), lr=self.params.lr)
        return self.opt

    def _target(self, logits: Tensor) -> Tensor:
        assert self.context is not None and self.context.teacher is not None
        with torch.no_grad():
            return self.context.teacher.denoise(logits.detach()).movedim(1, -1)

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        s = taps["student"]
        return ((self.aux(s.movedim(1, -1)) - self._target(s)) ** 2).mean()

    def update(self, step: int, batch: Batch, taps: dict[str, Any]) -> dict[str, float]:
        s = taps["student"]
        assert not s.requires_grad, "update receives detached taps"
        for _ in range(self.params.inner_steps):
            self.opt.zero_grad(set_to_none=True)
            loss = ((self.aux(s.movedim(1, -1)) - self._target(s)) ** 2).mean()
            loss.backward()
            self.opt.step()
        return {"aux_loss": float(loss.detach())}


@pytest.fixture(scope="module", autouse=True)
def components() -> Iterator[None]:
    ADAPTERS.add("test-denoiser", DenoisingSCPNet, description="test: SCPNet with denoise()", paper="tests",
                 consumes=tuple(DenoisingSCPNet.TAPS.values()))
    register_objective("test-aux-score", AuxScore, description="test: auxiliary network with own optimizer",
                       paper="tests", equation="mean (a(s) − denoise(s))²", shapes="voxel logits")
    yield
    ADAPTERS.remove("test-denoiser")  # other tests iterate over the registries
    OBJECTIVES.remove("test-aux-score")


def recipe(teacher_adapter: str = "test-denoiser") -> dict[str, Any]:
    r = tiny_recipe(steps=2)
    r["stages"]["teacher"]["model"]["adapter"] = teacher_adapter
    r["stages"]["student"]["distill"] = [{"name": "test-aux-score", "params": {"inner_steps": 2}}]
    return r


@pytest.fixture(scope="module")
def trained(components, tmp_path_factory) -> tuple[Pipeline, Any, dict[str, int]]:
    """One run of :func:`recipe` (read only by the tests below): the pipeline, the student's result, and the calls
    counted during the run."""
    pipe = Pipeline(recipe_from_dict(recipe()), tmp_path_factory.mktemp("aux") / "runs", quiet=True)
    CALLS.update(denoise=0, frozen_forward=0)
    _, student = pipe.run()
    return pipe, student, dict(CALLS)


@pytest.mark.xdist_group("objective_context")  # one worker runs the shared stage once
def test_an_objective_trains_its_own_network_and_calls_a_teacher_capability(trained) -> None:
    _, student, calls = trained
    # no objective reads a teacher tap: the teacher never runs forward, only denoise() is called
    assert calls["frozen_forward"] == 0 and calls["denoise"] > 0
    log = [json.loads(x) for x in (student.run_dir / "metrics.jsonl").read_text().splitlines()]
    assert all("aux_loss" in rec for rec in log if "loss" in rec)
    ckpt = load_checkpoint(student.run_dir / "checkpoints" / "last.pt")
    *task_states, state = ckpt["term_optimizers"]  # task losses first: they have no optimizer of their own
    assert task_states and not any(task_states)
    # its own Adam took inner_steps per student step (2 x 2), from the objective's update only
    assert [int(s["step"]) for s in state["state"].values()] == [4, 4]
    assert any(k.startswith("0.aux.") for k in ckpt["objectives"])


@pytest.mark.xdist_group("objective_context")  # one worker runs the shared stage once
def test_the_student_optimizer_leaves_an_objectives_own_parameters_alone(trained) -> None:
    from conftest import make_trainer
    from distilkit.engine.assemble.runs import load_run

    pipe = trained[0]
    stage = pipe.resolved.stages["student"]
    teacher = load_run(pipe.run_dir("teacher"), model=stage.teacher, info=pipe.resolved.data_info, role="teacher")
    trainer = make_trainer(pipe, "student", teacher)
    own = {id(p) for p in trainer.objectives[0].aux.parameters()}
    assert own and not own & {id(p) for p in trainer.trainable}
    assert not any(name.startswith("distill.") for name, _ in trainer.named_trainables())
    assert not own & {id(p) for g in trainer.optimizer.param_groups for p in g["params"]}


def test_validate_names_a_missing_teacher_capability(tmp_path) -> None:
    with pytest.raises(RecipeError, match=r"calls the teacher's denoise\(\), which adapter 'scpnet' does not provide"):
        Pipeline(recipe_from_dict(recipe(teacher_adapter="scpnet")), tmp_path / "runs", quiet=True)
