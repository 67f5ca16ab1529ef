"""A recipe's own taps (``model: {taps: {...}}``, ``teacher: {taps: {...}}``): a submodule's output recorded by a
forward hook, or another tap collapsed over height onto the bird's-eye plane."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class HookTapSpec(BaseModel):
    """A tap recorded from any submodule by its dotted path (no adapter code needed), or made from another tap of
    the model (``of``) by collapsing it over height (``collapse``): a ``bev_features`` tap of any voxel tap."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    module: str | None = Field(None, description="dotted path of the submodule, as in `model.named_modules()`")
    of: str | None = Field(None, description="instead of `module`: another tap of the model (the adapter's or the "
                                             "recipe's) whose value this one is made of, with `collapse`")
    kind: str = Field(..., description="tap kind of the recorded value (e.g. volume_features; bev_features with "
                                       "`collapse`)")
    at: str = Field("output", description="what is recorded: a registered recorder (`distilkit list recorders`): "
                                         "output, input (its first), method (the return value of `method`)")
    method: str | None = Field(None, description="with `at: method`: the submodule's method whose return value is "
                                                 "recorded (e.g. encode)")
    collapse: Literal["max", "mean"] | None = Field(
        None, description="the value ((B, C, X, Y, Z) or sparse voxels) reduced over height per channel onto the "
                          "(X, Y) plane, a bev_features tap: max or mean (sparse voxels: over a column's active "
                          "voxels, an empty column 0, the voxel-to-BEV release's scatter-max; a dense volume: over "
                          "every height)")

    @model_validator(mode="after")
    def _one_source(self) -> "HookTapSpec":
        if (self.module is None) == (self.of is None):
            raise ValueError("give the tap either `module` (a submodule to record) or `of` (another tap to collapse)")
        if self.of is not None and self.collapse is None:
            raise ValueError(f"a tap made `of: {self.of}` needs `collapse: max` or `collapse: mean`")
        if self.collapse is not None and self.kind != "bev_features":
            raise ValueError(f"a collapsed tap is a bev_features tap, not {self.kind}")
        return self


__all__ = ["HookTapSpec"]
