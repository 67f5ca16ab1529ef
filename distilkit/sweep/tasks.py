"""A sweep's tasks: one ``distilkit run`` each (a variant at a seed, or the upstream stages its runs wait on) and the
title it is shown and logged under, whichever launcher runs it (:mod:`~distilkit.sweep.runner` here or in parallel
processes, :mod:`~distilkit.sweep.slurm` on a cluster)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Task:
    """One ``distilkit run``: the variant's recipe at a seed, for ``stages`` (the variant, or its upstream)."""

    variant: str
    seed: int
    stages: tuple[str, ...]
    recipe_file: Path
    upstream_of: str = ""  # an upstream task: the variants whose runs wait on it, in words ("variants kd, dist")

    def argv(self, output: Path) -> list[str]:
        return ["run", str(self.recipe_file), "--seed", str(self.seed), "--output", str(output),
                "--stage", *self.stages]

    @property
    def key(self) -> tuple[str, int, tuple[str, ...]]:
        """What the task is, whatever its title's words: the variant it was made for, the seed, the stages."""
        return self.variant, self.seed, self.stages

    @property
    def title(self) -> str:
        if self.stages == (self.variant,):
            return f"{self.variant}, seed {self.seed}"
        users = self.upstream_of or f"variant {self.variant}"
        return f"{', '.join(self.stages)} (upstream of {users}), seed {self.seed}"


def variants_phrase(users: list[str], every: list[str]) -> str:
    """The variants an upstream task is shared by, in words: "variant kd", "variants kd, dist and 3 more", or
    "every variant" (of the sweep's ``every``)."""
    if len(users) > 1 and set(users) == set(every):
        return "every variant"
    if len(users) == 1:
        return f"variant {users[0]}"
    return "variants " + ", ".join(users[:4]) + (f" and {len(users) - 4} more" if len(users) > 4 else "")


__all__ = ["Task", "variants_phrase"]
