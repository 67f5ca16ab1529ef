"""Task losses and objectives as one term protocol: roles from taps or batch fields, unique term names."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import tiny_recipe
from distilkit.engine.train.pipeline import Pipeline
from conftest import make_trainer
from distilkit.engine.train.trainer import Trainer
from distilkit.errors import RecipeError
from distilkit.recipe import recipe_from_dict


def trainer_for(recipe: dict, tmp_path) -> Trainer:
    pipe = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True)
    return make_trainer(pipe, "teacher")


def test_a_recipe_points_a_batch_role_at_another_field_and_repeated_terms_all_count(tmp_path) -> None:
    r = tiny_recipe(distill=False)
    r["stages"]["teacher"]["task_losses"] = [{"name": "ce", "weight": 1.0},
                                             {"name": "ce", "weight": 0.5, "taps": {"target": "voxel_label"}}]
    trainer = trainer_for(r, tmp_path)
    assert [t.key for t in trainer.terms] == ["ce", "ce_2"]
    batch = trainer.first_batch()
    torch.manual_seed(0)
    terms = trainer.loss_terms(batch)
    torch.manual_seed(0)
    logits = trainer.student(batch)["logits"].detach()
    # naive: F.cross_entropy on each field; voxel_target marks invalid voxels 255, voxel_label does not
    assert not torch.equal(batch.targets["voxel_target"], batch.targets["voxel_label"])
    want_1 = F.cross_entropy(logits.double(), batch.targets["voxel_target"], ignore_index=255)
    want_2 = 0.5 * F.cross_entropy(logits.double(), batch.targets["voxel_label"], ignore_index=255)
    assert float(terms["ce"].detach()) == pytest.approx(float(want_1), rel=1e-5)
    assert float(terms["ce_2"].detach()) == pytest.approx(float(want_2), rel=1e-5)


def test_a_moved_batch_role_changes_the_stage_identity_and_the_default_does_not(tmp_path) -> None:
    def hashes(task_losses: list | None) -> str:
        r = tiny_recipe(distill=False)
        if task_losses is not None:
            r["stages"]["teacher"]["task_losses"] = task_losses
        return Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True).hashes["teacher"]

    default = hashes(None)
    assert hashes([{"name": "ce"}, {"name": "lovasz"}]) == default
    assert hashes([{"name": "ce", "taps": {"target": "voxel_target"}}, {"name": "lovasz"}]) == default
    assert hashes([{"name": "ce", "taps": {"target": "voxel_label"}}, {"name": "lovasz"}]) != default


def test_validate_names_a_batch_field_the_data_lacks_and_a_connector_without_a_teacher(tmp_path) -> None:
    r = tiny_recipe(distill=False)
    r["stages"]["teacher"]["task_losses"] = [{"name": "ce", "taps": {"target": "voxel_labels"}},
                                             {"name": "lovasz", "connector": "linear"}]
    with pytest.raises(RecipeError) as err:
        Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True)
    text = str(err.value)
    assert "stages.teacher.task_losses[0].taps.target" in text and "'voxel_labels'" in text
    assert "voxel_target" in text  # the fields it does have are listed
    assert "stages.teacher.task_losses[1].connector" in text and "reads no teacher tap" in text
