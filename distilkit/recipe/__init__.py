"""A recipe: its schema (:mod:`~distilkit.recipe.schema`), reading it from YAML with overrides
(:mod:`~distilkit.recipe.load`), its validation errors as lines a user reads (:mod:`~distilkit.recipe.problems`)
and its stages as a graph (:mod:`~distilkit.recipe.graph`). Everything is importable from ``distilkit.recipe``.
"""

from __future__ import annotations

from distilkit.recipe.schema import (SCHEMA_VERSION, MAX_NAME, MAX_LABEL, MAX_NOTE, HookTapSpec, ModelSpec,
                                     TeacherSpec, InitSpec, LabelsSpec, AuxSpec, LossSpec, ParamGroupSpec,
                                     ScheduleSpec, OptimizerSpec, HookSpec, TrainSpec, StageSpec, DataSpec,
                                     ReportSpec, Recipe)
from distilkit.recipe.problems import format_loc, model_keys, pydantic_problems, unknown_key_message
from distilkit.recipe.load import load_recipe, parse_overrides, parse_yaml, recipe_from_dict, set_path
from distilkit.recipe.graph import needed_stages, stage_order

__all__ = [
    "AuxSpec", "DataSpec", "HookSpec", "HookTapSpec", "InitSpec", "LabelsSpec", "LossSpec", "MAX_LABEL", "MAX_NAME",
    "MAX_NOTE", "ModelSpec", "OptimizerSpec", "ParamGroupSpec", "Recipe", "ReportSpec", "SCHEMA_VERSION",
    "ScheduleSpec", "StageSpec", "TeacherSpec", "TrainSpec", "format_loc", "load_recipe", "model_keys",
    "needed_stages", "parse_overrides", "parse_yaml", "pydantic_problems", "recipe_from_dict", "set_path",
    "stage_order", "unknown_key_message"
]
