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


def seeds_text(seeds: list[int]) -> str:
    """``seed 3``, ``seeds 1–5``, ``seeds 0, 2–4, 7``: runs of consecutive seeds as ranges."""
    seeds = sorted(set(seeds))
    parts: list[str] = []
    start = prev = seeds[0]
    for s in [*seeds[1:], None]:
        if s is not None and s == prev + 1:
            prev = s
            continue
        parts.append(str(start) if start == prev else f"{start}–{prev}" if prev > start + 1 else f"{start}, {prev}")
        if s is not None:
            start = prev = s
    return ("seed " if len(seeds) == 1 else "seeds ") + ", ".join(parts)


def missing_text(missing: list[tuple[str, int]], every: list[str]) -> list[str]:
    """The runs not finished, variants with the same seeds missing together, in the sweep's order: ``every variant
    (seeds 1–5)``, ``nst_50, pvkd_1 (seed 0)`` — not one entry a run (a sweep under way misses hundreds)."""
    by_variant: dict[str, list[int]] = {}
    for variant, seed in missing:
        by_variant.setdefault(variant, []).append(seed)
    groups: dict[tuple[int, ...], list[str]] = {}
    for variant in every:
        if variant in by_variant:
            groups.setdefault(tuple(sorted(by_variant[variant])), []).append(variant)
    return [f"{'every variant' if len(names) == len(every) > 1 else ', '.join(names)} ({seeds_text(list(seeds))})"
            for seeds, names in groups.items()]


__all__ = ["Task", "missing_text", "seeds_text", "variants_phrase"]
