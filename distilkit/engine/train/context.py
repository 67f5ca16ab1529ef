"""What the stages of one recipe run share, and nothing of how they are ordered: the recipe resolved, the identities
that name the stages' run folders, the data (each split generated or read once, shared by the stages), the
checkpoints of upstream stages, the console and the processes of the run. A
:class:`~distilkit.engine.train.stage.StageRun` reads it; the :class:`~distilkit.engine.train.pipeline.Pipeline` is
one that also orders, locks and runs the stages."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from distilkit.engine.assemble.resolve import resolve
from distilkit.engine.store.identity import stage_hashes
from distilkit.recipe import Recipe, load_recipe
from distilkit.registry import DATASETS


class RecipeRun:
    """One recipe resolved for a run in ``output``: its stages' folders, its data and its upstream weights."""

    def __init__(self, recipe: Recipe | str | Path, output: str | Path = "runs", console: Any = None,
                 quiet: bool = False, seed: int | None = None, overrides: dict[str, Any] | None = None) -> None:
        from distilkit.sparse.choice import requested

        requested()  # DISTILKIT_SPARSE names a backend that exists: checked before any stage starts
        self.source = str(recipe) if not isinstance(recipe, Recipe) else "recipe"
        if overrides and isinstance(recipe, Recipe):
            raise ValueError("overrides apply to a recipe file; change a Recipe object with model_copy")
        self.recipe = recipe if isinstance(recipe, Recipe) else load_recipe(recipe, overrides)
        self.overrides = dict(overrides or {})  # recorded beside each stage's resolved configuration
        if seed is not None:  # a seed from the command line: a different identity for every stage
            self.recipe = self.recipe.model_copy(update={"seed": seed})
        self.resolved = resolve(self.recipe, self.source)
        self.root = Path(output) / self.recipe.name
        self.hashes, self.configs = stage_hashes(self.resolved)
        self.quiet = quiet
        if console is None:
            from distilkit.console import make_console

            console = make_console(quiet=quiet)
        self.console = console
        self._data: dict[str, Any] = {}  # split -> dataset
        self._world: Any = None  # the processes of this run: set in run() from torchrun's environment

    @property
    def world(self) -> Any:
        """The processes of this run (:class:`~distilkit.engine.train.distributed.World`; one until run() reads
        torchrun's environment)."""
        if self._world is None:
            from distilkit.engine.train.distributed import SINGLE

            self._world = SINGLE
        return self._world

    @world.setter
    def world(self, world: Any) -> None:
        self._world = world

    def share_data(self, store: dict[str, dict[str, Any]]) -> None:
        """Share datasets with the other pipelines in ``store`` that have the same data configuration (a sweep's
        runs read their scenes once)."""
        key = json.dumps({"dataset": self.recipe.data.dataset,
                          "params": self.resolved.data_params.model_dump(mode="json")}, sort_keys=True)
        self._data = store.setdefault(key, self._data)

    def run_dir(self, name: str) -> Path:
        return self.root / f"{name}-{self.hashes[name]}"

    def weights(self, name: str, which: str = "best") -> Path:
        """The checkpoint holding stage ``name``'s weights: its own, or for an evaluate-only stage (``steps: 0``, which
        writes none) the one it was initialised from, followed back to a trained stage or a weights file."""
        from distilkit.engine.assemble.runs import checkpoint_path

        spec = self.resolved.stages[name].spec
        if spec.train.steps == 0 and spec.init is not None:
            if spec.init.from_ is not None:
                return self.weights(spec.init.from_, spec.init.which)
            return Path(spec.init.checkpoint or "").expanduser()
        return checkpoint_path(self.run_dir(name), which)

    def dataset(self, split: str) -> Any:
        """The split's samples, each with its ``sample_id`` (generated or read once, shared by the stages)."""
        from distilkit.data.samples import Split

        if split not in self._data:
            entry = DATASETS.entry(self.recipe.data.dataset)
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            with Progress(TextColumn(f"[cyan]data[/] {self.recipe.data.dataset}/{split}"), BarColumn(),
                          MofNCompleteColumn(), TimeRemainingColumn(), console=self.console, transient=True) as prog:
                task = prog.add_task("gen", total=None)
                self._data[split] = Split(entry.obj(self.resolved.data_params, split,
                                                    lambda i, n: prog.update(task, completed=i, total=n)), split)
            for note in getattr(self._data[split].dataset, "notes", []):  # e.g. frames a folder leaves out
                self.console.print(f"[yellow]data {split}:[/] {note}")
        return self._data[split]

    @property
    def collate(self) -> Any:
        """The dataset's registered collate (samples -> :class:`~distilkit.data.batch.Batch`, with the sample ids)."""
        from distilkit.data.samples import IdCollate

        return IdCollate(DATASETS.entry(self.recipe.data.dataset).meta["collate"])

    def prediction_splits(self, name: str) -> list[str]:
        """The splits whose predictions stage ``name`` publishes: its own ``publish`` and what the stages that read
        labels from it need."""
        wanted = set(self.resolved.stages[name].spec.publish)
        for stage in self.resolved.stages.values():
            labels = stage.spec.labels
            if labels is not None and labels.from_ == name:
                wanted |= set(labels.splits)
        return [s for s in ("train", "val", "test") if s in wanted and self.has_split(s)]

    def has_split(self, split: str) -> bool:
        return self.resolved.has_split(split)


__all__ = ["RecipeRun"]
