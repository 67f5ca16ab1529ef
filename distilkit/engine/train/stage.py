"""One stage run, with one owner: build → loop → evaluate → publish.

* **build**: the run folder and its resolved configuration, the stage's seed (once), the device, the frozen
  teacher and the initial weights (both rebuilt from upstream runs by
  :func:`~distilkit.engine.assemble.runs.load_run`), the data loaders, and the
  :class:`~distilkit.engine.train.trainer.Trainer` (student, terms, optimizer);
* **loop**: batches from the loader (:mod:`~distilkit.engine.train.loader`), one optimizer step each, the lifecycle
  hooks (:mod:`~distilkit.engine.hooks`) around it; a run started again resumes from ``last.pt`` (models, optimizers,
  RNG and the batch order);
* **evaluate**: the best-validation and the last checkpoint on the test split (the validation split where the data
  has no test split) with the stage's metrics, each process scoring its share;
* **publish**: ``summary.json`` (which marks the stage finished), ``preview.npz`` and the run report.

It reads what the recipe's stages share (:class:`~distilkit.engine.train.context.RecipeRun`: the resolved recipe, the
data, upstream weights); the pipeline (:mod:`~distilkit.engine.train.pipeline`) only orders, hashes and locks stages.

Why one module: the four phases share one run's state (its device, loaders, checkpoints and trainer) and read top
to bottom in the order they happen.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import yaml

from distilkit import __version__
from distilkit.engine.store.checkpoints import Checkpoints
from distilkit.engine.store.summary import read_summary
from distilkit.engine.hooks import CheckpointHook, EvalHook, Hook, LogHook, Loop, ProgressHook
from distilkit.engine.train.randomness import seed_everything
from distilkit.files import atomic_write_json, atomic_write_text
from distilkit.repro import mkl_cbwr, processor, vector_math_warmed
from distilkit.report.scenes import SCENE_COUNTS
from distilkit.engine.train.loader import BatchPlan, eval_batches, resolve_workers, train_batches
from distilkit.engine.assemble.runs import load_run
from distilkit.engine.train.auxiliary import with_aux_inputs
from distilkit.engine.assemble.devices import pick_device

if TYPE_CHECKING:
    from distilkit.engine.train.context import RecipeRun
    from distilkit.engine.train.trainer import Trainer


@dataclass
class StageResult:
    name: str
    run_dir: Path
    summary: dict[str, Any]
    reused: bool


class StageRun:
    """The run of stage ``name`` of a pipeline's recipe in ``run_dir`` (the caller holds the stage's lock)."""

    def __init__(self, pipeline: "RecipeRun", name: str, run_dir: Path, stop_after: int | None = None) -> None:
        from distilkit.engine.store.identity import stage_seed

        self.pipeline, self.name, self.run_dir, self.stop_after = pipeline, name, run_dir, stop_after
        self.stage = pipeline.resolved.stages[name]
        self.info = pipeline.resolved.data_info
        self.world = pipeline.world
        self.seed = stage_seed(pipeline.resolved, self.stage)
        self.spec = self.stage.spec.train
        self.workers = resolve_workers(self.spec.workers)
        self.checkpoints = Checkpoints(run_dir / "checkpoints", self.world.main)
        self.trainer: Trainer | None = None
        self.aux: list[tuple[Any, Any]] = []  # (resolved aux, its frozen model)
        self.eval_progress: Any = None  # where an evaluation shows its progress (the stage's bar), if anywhere
        self.device = pick_device(self.spec.device)
        self.nondeterministic: list[str] = []  # ops that ran without a deterministic variant (warn_only)
        self.sparse_backends: set[str] = set()  # which backends computed its sparse convolutions
        self.live: Loop | None = None  # the loop, once built: its hooks hear of a failure or a stop

    # -- the whole run -----------------------------------------------------------------------
    def run(self) -> StageResult | None:
        """Reuse the finished stage, or build, train, evaluate and publish it (None: stopped early on request)."""
        done = read_summary(self.run_dir)
        if done is not None:
            self.pipeline.console.print(f"[green]✓[/] stage [bold]{self.name}[/] reused from {self.run_dir}")
            self.publish_predictions()  # what a later stage now asks of it
            # the label is cosmetic (not part of the identity): show the recipe's current one
            return StageResult(self.name, self.run_dir, {**done, "label": self.stage.spec.label or self.name}, True)
        self._prepare_folder()
        try:
            return self._train_and_publish()
        except BaseException as exc:  # a failure, SIGTERM, Ctrl-C: the hooks (the trackers) record it
            if self.live is not None:
                self.live.aborted(exc)
            raise

    def _train_and_publish(self) -> StageResult | None:
        """Build, train, evaluate and publish (None: stopped early on request)."""
        from distilkit.console import progress_bar, stage_progress
        from distilkit.engine.train.oom import is_out_of_memory, out_of_memory
        from distilkit.repro import nondeterministic_ops
        from distilkit.sparse.backend import record as record_backends

        with nondeterministic_ops() as self.nondeterministic, record_backends() as self.sparse_backends:
            try:
                with stage_progress(self.pipeline.console, self.name) as bar:
                    self.eval_progress = bar.evaluation
                    self.build()
                    loop = self.loop(bar)
                assert self.trainer is not None
                if loop.step < self.trainer.total_steps:
                    kept = (f"a resume starts from last.pt at step {loop.saved}" if loop.saved else
                            "no checkpoint yet: a resume starts from step 0")
                    self.pipeline.console.print(f"stage {self.name} stopped after {loop.step} steps ({kept})")
                    return None
                split = self.report_split()
                best = self.best_model()  # read once: scored on the test split, previewed on a validation scene
                test = {}
                if split is not None:
                    scoring = f"{self.name}: scoring {split}"
                    with progress_bar(self.pipeline.console, scoring, transient=True) as advance:
                        self.eval_progress = lambda done, total: advance(done, total) if done is not None else None
                        test = self.score(split, best)
                self.eval_progress = None
                self.write_preview(best)
                self.publish_predictions(best[0] if best is not None else None)
            except (RuntimeError, MemoryError) as exc:  # out of memory: one line that says what to lower
                if not is_out_of_memory(exc):
                    raise
                kept = self.checkpoints.kept() if self.trainer is not None else "no checkpoint had been written yet"
                raise out_of_memory(self.stage, self.info, exc, kept) from None
        return self.publish(loop, split, test)

    def report_split(self) -> str | None:
        """The split scores are reported on: test, else validation (and the summary says so), else none (a stage
        trained on everything, e.g. for a benchmark submission). A split whose dataset says it has no targets
        (``has_targets``: SemanticKITTI's hidden test sequences) is predicted, never scored."""
        def scored(split: str) -> bool:
            return self.pipeline.has_split(split) and bool(getattr(self.pipeline.dataset(split), "has_targets", True))

        return next((s for s in ("test", "val") if scored(s)), None)

    def _prepare_folder(self) -> None:
        """The folder, without a killed writer's temporary files, and the stage's resolved configuration."""
        if not self.world.main:
            return
        p = self.pipeline
        self.run_dir.mkdir(parents=True, exist_ok=True)
        for stale in [*self.run_dir.glob(".*"), *self.run_dir.glob("checkpoints/.*")]:
            stale.unlink(missing_ok=True)
        atomic_write_text(self.run_dir / "recipe.resolved.yaml",
                          yaml.safe_dump({"recipe": p.recipe.name, "stage": self.name, "hash": p.hashes[self.name],
                                          "distilkit": __version__,
                                          **({"overrides": p.overrides} if p.overrides else {}),
                                          **p.configs[self.name]}, sort_keys=False))

    # -- build -------------------------------------------------------------------------------
    def upstream(self, field: str) -> Path:
        """The checkpoint an upstream edge (``teacher``, ``init``) reads: a stage's run folder or a file."""
        src = getattr(self.stage.spec, field)
        if src.from_ is not None:
            return self.pipeline.weights(src.from_, src.which)
        return Path(src.checkpoint or "").expanduser()

    def split(self, name: str) -> Any:
        """The stage's samples of split ``name``: the data's, with labels from a stage's predictions where the
        recipe asks (``labels``)."""
        from distilkit.engine.store.predictions import LabelOverlay, PredictionStore

        data = self.pipeline.dataset(name)
        labels = self.stage.spec.labels
        if labels is None or name not in labels.splits:
            return data
        store = PredictionStore(self.pipeline.run_dir(labels.from_) / "predictions" / name)
        return LabelOverlay(data, store, labels.field, labels.keep, self.info.classes.ignore_index, labels.unlabelled)

    def prepare(self, batch: Any) -> Any:
        """A batch to evaluate or publish on the device, with the inputs the auxiliary models give (their taps, under
        no_grad)."""
        return with_aux_inputs(batch.to(self.device), self.aux)

    def prepare_training(self, batch: Any) -> Any:
        """A training batch on the device, with the inputs the auxiliary models that run in training give."""
        return with_aux_inputs(batch.to(self.device), self.aux, training=True)

    def load_aux(self) -> None:
        """The frozen auxiliary models (``aux``), each from its stage's checkpoint (once)."""
        if len(self.aux) != len(self.stage.aux):
            self.aux = [(aux, load_run(self.pipeline.weights(aux.stage, aux.which), model=aux.model,
                                       info=self.info, device=self.device, role=f"aux model {aux.name!r}"))
                        for aux in self.stage.aux]

    def build(self) -> "Trainer":
        """The stage's seed, then the frozen teacher and auxiliary models (drawing nothing from the seeded stream),
        the initial weights and the trainer on this process's batches."""
        from distilkit.engine.train.trainer import Trainer

        seed_everything(self.seed)
        self.load_aux()
        from distilkit.engine.train import controls

        teacher, store = None, None
        stored = self.stage.spec.teacher is not None and self.stage.spec.teacher.store is not None
        control = self.stage.spec.teacher.control if self.stage.spec.teacher is not None else None
        if self.stage.teacher is not None and self.stage.distill and self.stage.ema is None and not stored:
            teacher = (controls.random_teacher(self.stage.teacher, self.info, self.seed, self.device)
                       if control == "random" else  # the architecture with random weights, not the checkpoint's
                       load_run(self.upstream("teacher"), model=self.stage.teacher, info=self.info,
                                device=self.device, role="teacher"))  # an EMA: the trainer's
        init = None
        if self.stage.spec.init is not None:
            path = self.upstream("init")
            init = (self.stage.student.cls.read_weights(str(path)), self.stage.spec.init.strict, f"init {path}")
        train_set, group, augmentation = self.split("train"), 1, None
        if self.spec.augment is not None:  # each training sample under a drawn transform, every field alike
            from distilkit.data.augment import Augmentation

            augmentation = Augmentation(self.spec.augment, self.info.grid)
            group = augmentation.draws
        if stored and self.stage.distill:  # the teacher's outputs from its store, built here if not yet
            from distilkit.engine.train.teacher_store import ensure_store

            devices = [self.device] if self.device.type == "cuda" else []
            with torch.random.fork_rng(devices=devices):  # building draws nothing from the stage's stream
                store = ensure_store(self, train_set, augmentation)
        if augmentation is not None:
            from distilkit.data.augment import Augmented

            train_set = Augmented(train_set, augmentation)
        collate = self.pipeline.collate
        if control == "shuffled" and self.stage.distill:  # each sample meets another's teacher outputs
            sigma = controls.cycle(len(train_set), self.seed)
            if store is not None:
                store = controls.PartnerStore(store, sigma)
            else:
                train_set, collate = controls.Partnered(train_set, sigma), controls.WithPartner(collate)
        plan = BatchPlan(len(train_set), self.spec.batch_size, self.seed, self.world, group)
        self.trainer = Trainer(self.stage, self.info, train_set, plan, self.device, collate=collate,
                               teacher=teacher, init_weights=init, world=self.world, prepare=self.prepare_training,
                               store=store)
        self.trainer.kept = self.checkpoints.kept
        return self.trainer

    def hooks(self, on_step: Any) -> list[Hook]:
        """The loop's hooks: log, progress, evaluation (best.pt), checkpoint (last.pt), then the recipe's."""
        from distilkit.registry import HOOKS

        assert self.stage.metric is not None
        own: list[Hook] = [LogHook(), ProgressHook(on_step)]
        if self.pipeline.has_split("val"):  # no validation split: nothing selects a best checkpoint
            own.append(EvalHook(self.stage.metric.key, self.stage.metric.higher_is_better))
        own.append(CheckpointHook())
        return own + [HOOKS.get(h.name)(h.params) for h in self.stage.hooks]

    # -- loop --------------------------------------------------------------------------------
    def loop(self, on_step: Any) -> Loop:
        """Train from the start or from ``last.pt`` to the last step (or ``stop_after``)."""
        from distilkit.engine.train import stop as stopping
        from distilkit.engine.train.randomness import set_rng_state

        trainer = self.trainer
        assert trainer is not None
        loop = Loop(self.name, self.run_dir, self.spec, trainer.total_steps, trainer.steps_per_epoch,
                    self.spec.eval_every or trainer.steps_per_epoch, self.world.main,
                    per_class=self.per_class(), _log=self.log, _evaluate=lambda: self.evaluate(self.split("val")),
                    _save=lambda which: self.save(which, loop), _warn=self.warn)
        self.live = loop
        unreadable: list[Path] = []  # tried first and passed over: resume reads last.pt, then last.prev.pt

        def passed_over(exc: Exception, path: Path) -> None:
            unreadable.append(path)
            self._unreadable(exc, path)

        ckpt = self.checkpoints.resume(on_unreadable=passed_over)
        if ckpt is not None:
            trainer.load_state(ckpt)
            set_rng_state(ckpt["rng"])
            trainer.rank_rng(int(ckpt["step"]))
            loop.step, loop.best = int(ckpt["step"]), ckpt["best"]
            loop.saved = loop.step
            self._truncate_log(loop.step)
            self.log({"event": "resume", "step": loop.step})
            read = "last.prev.pt" if any(p.name == "last.pt" for p in unreadable) else "last.pt"
            self.pipeline.console.print(f"stage [bold]{self.name}[/]: resumed from step {loop.step} of "
                                        f"{trainer.total_steps} ({read})", highlight=False)
        elif trainer.init_left_out is not None:
            self.log({"event": "init", "from": str(self.upstream("init")), "left_out": trainer.init_left_out})
        loop.hooks = self.hooks(on_step)
        stop = trainer.total_steps if self.stop_after is None else min(trainer.total_steps, self.stop_after)
        trainer.student.train()
        loop.emit("before_train")
        batches = iter(train_batches(trainer.train_set, trainer.plan, trainer.collate, loop.step, stop, self.workers))
        while True:
            t0 = time.perf_counter()  # the wait for the loader (its workers read, collate and read a teacher store)
            batch = next(batches, None)
            loop.waited += time.perf_counter() - t0
            if batch is None:
                break
            loop.emit("before_step")
            values = trainer.train_step(self.prepare_training(batch), loop.step)
            loop.values = {**values, "lr": trainer.optimizer.param_groups[0]["lr"]}
            loop.step += 1
            loop.evaluated = False
            loop.emit("after_step")
            if self.world.any(stopping.requested()) and loop.step < trainer.total_steps:  # SIGTERM, or a sweep gone
                loop.save("last")
                self.log({"event": "stopped", "step": loop.step})
                raise KeyboardInterrupt
        if loop.last_scores is None and self.pipeline.has_split("val"):
            loop.last_scores = self.evaluate(self.split("val"))
        loop.seconds = time.perf_counter() - loop.t0
        loop.emit("after_train")
        return loop

    def per_class(self) -> dict[str, list[str]]:
        """Each per-class score's key (the first metric's as it is, the others' as ``<name>.<key>``, as
        :func:`~distilkit.engine.train.evaluate.evaluate` reports them) -> the class of each of its entries."""
        names = list(self.info.classes.names)
        out = {}
        for i, metric in enumerate(self.stage.metrics):
            if metric.cls.PER_CLASS is not None:
                key = metric.cls.PER_CLASS[0]
                out[key if i == 0 else f"{metric.name}.{key}"] = names[metric.cls.PER_CLASS_FROM:]
        return out

    def warn(self, text: str) -> None:
        """One warning line (a tracker that failed): on the console (standard error under ``-q``) and in
        ``metrics.jsonl``."""
        import sys

        self.log({"event": "warning", "step": self.live.step if self.live is not None else 0, "text": text})
        if self.pipeline.quiet:
            print(f"warning: {text}", file=sys.stderr)
        else:
            self.pipeline.console.print(f"[yellow]warning: {text}[/]", highlight=False, soft_wrap=True)

    def log(self, record: dict[str, Any]) -> None:
        """A record appended to ``metrics.jsonl`` (the main process writes)."""
        if not self.world.main:
            return
        self.run_dir.mkdir(parents=True, exist_ok=True)
        with open(self.run_dir / "metrics.jsonl", "a", encoding="utf-8") as f:
            f.write(json.dumps(record) + "\n")

    def _truncate_log(self, step: int) -> None:
        """Drop log records written after ``step`` (the checkpoint a resume starts from): no duplicates."""
        path = self.run_dir / "metrics.jsonl"
        if not path.is_file() or not self.world.main:
            return
        keep = []
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                rec = json.loads(line)
            except ValueError:  # a line cut by a kill
                continue
            if int(rec.get("step", 0)) <= step:
                keep.append(line)
        atomic_write_text(path, "".join(f"{line}\n" for line in keep))

    def _unreadable(self, exc: Exception, path: Path) -> None:
        self.log({"event": "unreadable_checkpoint", "path": str(path), "error": str(exc)})
        if not self.pipeline.quiet:
            self.pipeline.console.print(f"[yellow]{exc}; trying the previous checkpoint[/]")

    def save(self, which: str, loop: Loop) -> None:
        """``last.pt`` (everything to resume from) or ``best.pt`` (the student and the scores that chose it)."""
        from distilkit.engine.train.randomness import rng_state

        assert self.trainer is not None
        if which == "last":
            self.checkpoints.write_last({**self.trainer.state(full=True), "step": loop.step, "best": loop.best,
                                         "rng": rng_state()}, loop.step)
        else:
            self.checkpoints.write_best({**self.trainer.state(full=False), "step": loop.step,
                                         "scores": json.dumps(loop.best["scores"])})

    # -- evaluate ----------------------------------------------------------------------------
    def evaluate(self, dataset: Any, model: Any = None, scenes: bool = False) -> dict[str, Any]:
        """Scores of the student (or ``model``) on ``dataset`` with the stage's metrics, each process scoring its
        share; a stochastic model draws the same noise at every evaluation (the stage's seed, in a stream of its
        own that training does not see)."""
        from distilkit.engine.train.evaluate import evaluate

        assert self.trainer is not None
        return evaluate(model if model is not None else self.trainer.student, dataset, self.spec.batch_size,
                        self.device, self.pipeline.collate, self.stage.metrics, world=self.world,
                        workers=self.workers, seed=self.seed, prepare=self.prepare,
                        progress=self.eval_progress if self.world.main else None, scenes=scenes)

    def best_model(self) -> tuple[Any, int] | None:
        """The student of ``best.pt`` and its step (None before the first evaluation); every process reads the file
        the main process wrote, so all score the same models."""
        self.world.barrier()
        if not (self.run_dir / "checkpoints" / "best.pt").is_file():
            return None
        from distilkit.engine.assemble.runs import checkpoint_step

        model = load_run(self.run_dir, "best", model=self.stage.student, info=self.info, device=self.device,
                         role="student", frozen=False)
        return model, checkpoint_step(self.run_dir, "best")

    def score(self, split: str, best: tuple[Any, int] | None) -> dict[str, Any]:
        """Scores on ``split`` of the best-validation checkpoint and of the last one (once where the best is the
        last step: the same weights)."""
        assert self.trainer is not None
        dataset = self.split(split)
        same = best is None or best[1] == self.trainer.total_steps
        out: dict[str, Any] = {"last": self.evaluate(dataset, scenes=same), "last_step": self.trainer.total_steps}
        if not same:
            assert best is not None
            out["best"], out["best_step"] = self.evaluate(dataset, best[0], scenes=True), best[1]
        else:
            out["best"], out["best_step"] = out["last"], self.trainer.total_steps
        self.write_scene_counts(split, out["best"].pop("scenes", None), out["best_step"])
        return out

    def write_scene_counts(self, split: str, scenes: dict[str, Any] | None, step: int) -> None:
        """``scene_counts.npz``: the best checkpoint's per-scene intersections and unions on ``split`` (ids, arrays
        and class names only: loaded without pickle), for the report's bootstrap over test scenes
        (:mod:`distilkit.report.scenes`); kept out of summary.json, whose size they would multiply."""
        if scenes is None or not self.world.main:
            return
        path, tmp = self.run_dir / SCENE_COUNTS, self.run_dir / ".scene_counts.tmp.npz"
        np.savez_compressed(tmp, ids=np.array(scenes["ids"], dtype=str), inter=scenes["inter"],
                            union=scenes["union"], split=np.array(split), step=np.array(step),
                            classes=np.array(self.info.classes.names[1:], dtype=str))
        os.replace(tmp, path)

    # -- publish -----------------------------------------------------------------------------
    def write_preview(self, best: tuple[Any, int] | None) -> Path | None:
        """``preview.npz``: the metric's bird's-eye view of the best checkpoint (else the current student) on the
        first validation scene, with the class names and colours to draw it (arrays only: loaded without pickle)."""
        import numpy as np

        from distilkit.engine.train.evaluate import preview

        assert self.trainer is not None and self.stage.metric is not None
        if not self.world.main:
            return None
        shown = next((s for s in ("val", "test") if self.pipeline.has_split(s)), None)
        if shown is None:
            return None
        model = best[0] if best is not None else self.trainer.student
        view = preview(model, self.split(shown), self.device, self.pipeline.collate, self.stage.metric.cls,
                       seed=self.seed, prepare=self.prepare)
        if view is None:
            return None
        classes = self.info.classes
        path, tmp = self.run_dir / "preview.npz", self.run_dir / ".preview.tmp.npz"
        np.savez_compressed(tmp, **view, class_names=np.array(classes.names),
                            class_colours=np.array(classes.colours, dtype=np.uint8),
                            step=np.array(best[1] if best is not None else self.trainer.total_steps))
        os.replace(tmp, path)
        return path

    def publish_predictions(self, model: Any = None) -> list[str]:
        """Publish the best model's predictions of the splits later stages (or the recipe's ``publish``) ask for
        and that are not published yet; the splits written."""
        from distilkit.engine.store.predictions import is_published, publish

        wanted = [s for s in self.pipeline.prediction_splits(self.name)
                  if not is_published(self.run_dir / "predictions" / s)]
        if not wanted or not self.world.main:
            self.world.barrier()
            return []
        if model is None:
            self.load_aux()  # a reused stage predicts with its auxiliary models too
            model = load_run(self.run_dir, "any", model=self.stage.student, info=self.info, device=self.device)
        kind = self.stage.student.taps[self.stage.student.cls.PREDICTION_TAP]
        for split in wanted:
            with self.pipeline.console.status(f"stage {self.name}: publishing its predictions of {split}"):
                batches = eval_batches(self.pipeline.dataset(split), self.spec.batch_size, self.pipeline.collate,
                                       workers=self.workers)
                publish(model, batches, self.run_dir / "predictions" / split, kind, self.prepare)
        self.world.barrier()
        return wanted

    def publish(self, loop: Loop, split: str | None, test: dict[str, Any]) -> StageResult:
        """``summary.json`` (the stage is finished) and the run report, by the main process."""
        assert self.trainer is not None and self.stage.metric is not None
        stage, p = self.stage, self.pipeline
        summary = {
            "status": "finished", "stage": self.name, "hash": p.hashes[self.name], "label": stage.spec.label or self.name,
            "adapter": stage.student.adapter, "input": stage.student.cls.describe(stage.student.params),
            "teacher": stage.teacher_from or (stage.spec.teacher.checkpoint or ("ema" if stage.ema else None)
                                              if stage.spec.teacher else None),
            "teacher_control": stage.spec.teacher.control if stage.spec.teacher and stage.distill else None,
            "objectives": [f"{t.name}×{t.weight:g}" for t in stage.distill], "seed": self.seed,
            "processes": self.world.size, "threads": torch.get_num_threads(),  # rounding depends on them
            "versions": {"torch": torch.__version__, "numpy": np.__version__},  # numpy's streams: within a version
            "deterministic": torch.are_deterministic_algorithms_enabled(), "cpu": processor(), "mkl_cbwr": mkl_cbwr(),
            "vector_math_warmed": vector_math_warmed(),  # MKL VML's first calls made in one thread (repro)
            "classes": {"names": list(self.info.classes.names),
                        "colours": [list(c) for c in self.info.classes.colours]},
            "steps": loop.step, "train_seconds": round(loop.seconds, 2), "input_wait_seconds": round(loop.waited, 3),
            "metric": {"name": stage.metric.name, "key": stage.metric.key},
            "best": loop.best, "last": loop.last_scores, "report_split": split, "test": test,
            "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S"),
        }
        if self.sparse_backends:  # which implementation computed the sparse convolutions (DISTILKIT_SPARSE)
            summary["sparse_backend"] = sorted(self.sparse_backends)
        if summary["deterministic"] and "STRICT" not in (summary["mkl_cbwr"] or "STRICT"):
            p.console.print(f"[yellow]stage {self.name}: MKL ran with MKL_CBWR={summary['mkl_cbwr']} (not STRICT): its "
                            "sums may depend on memory alignment, so this run may not repeat bitwise in another "
                            "process[/]", highlight=False)
        if self.nondeterministic:  # this run is not bitwise repeatable: say which ops made it so
            summary["nondeterministic_ops"] = list(self.nondeterministic)
            for op in self.nondeterministic:
                p.console.print(f"[yellow]stage {self.name}: {op} has no deterministic variant on the "
                                f"{self.device.type}; this run is not bitwise repeatable[/]", highlight=False)
        if not self.world.main:
            return StageResult(self.name, self.run_dir, summary, reused=False)
        atomic_write_json(self.run_dir / "summary.json", summary)
        try:
            from distilkit.report.run import write_run_report

            write_run_report(self.run_dir)
        except Exception as exc:  # a plotting problem must not lose a finished stage
            p.console.print(f"[yellow]{self.run_dir / 'report.md'} not written: {exc}[/]")
        loop.published(summary)  # the trackers: the report, its plots and the final scores
        return StageResult(self.name, self.run_dir, summary, reused=False)


__all__ = ["StageResult", "StageRun", "read_summary"]
