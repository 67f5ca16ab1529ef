"""The optimisation of one stage: its student, the frozen teacher it reads, task losses, distillation objectives,
connectors and the optimizer, and one training step.

Per step (:meth:`Trainer.train_step`): ``s_out = student(batch)``; the teacher's outputs under ``no_grad`` when a
term reads a teacher tap; ``loss = sum_j w_j task_j + sum_i w_i objective_i(taps)``; backward, a finite-gradient
check, clipping, the optimizer step, then each objective's own ``update``. A stage that is its own teacher
(``teacher: {ema: ...}``) moves its moving-average teacher before the step's forward (:mod:`~distilkit.engine.train.ema`); a
teacher runs in its ``teacher.mode`` (:mod:`~distilkit.engine.train.teacher_mode`). The stage's run (the loop, its hooks,
evaluation, checkpoints) is :mod:`distilkit.engine.train.stage`; this class is what it optimises.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import torch
from torch import Tensor, nn

from distilkit.adapter import Adapter
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.engine.train.distributed import SINGLE, World, sync_batchnorm
from distilkit.engine.train.ema import EmaTeacher
from distilkit.engine.train.groups import freeze, param_groups
from distilkit.engine.train.teacher_mode import apply_mode, evaluating, load_teacher_buffers, teacher_buffers
from distilkit.weights import load_weights
from distilkit.engine.train.loader import BatchPlan, Collate
from distilkit.engine.train.optim import lr_factor, weight_factor
from distilkit.engine.assemble.resolved import ResolvedStage, ResolvedTerm
from distilkit.engine.assemble.runs import build_model
from distilkit.errors import DistilkitError, NonFiniteLossError
from distilkit.objectives.connectors import Connector
from distilkit.taps import check_tap, to_float32
from distilkit.term import Term, TermContext


@dataclass
class StageTerm:
    """One term of the stage loss as the trainer runs it: the name it is logged under (``kd_`` for
    objectives), the resolved spec, its module and the connector of its student tap (objectives)."""

    key: str
    what: str  # "task loss" or "objective"
    spec: ResolvedTerm
    module: Term
    connector: nn.Module | None


class Trainer:
    """Built from the stage's random stream as the caller seeded it: the student first (then ``init_weights`` over
    it), the terms, their connectors and layers sized from batch 0 of ``plan``, the optimizer."""

    def __init__(self, stage: ResolvedStage, info: DataInfo, train_set: Any, plan: BatchPlan, device: torch.device,
                 *, collate: Collate, teacher: Adapter | None = None,
                 init_weights: tuple[dict[str, Any], bool, str] | None = None, world: World = SINGLE,
                 prepare: Callable[[Batch], Batch] | None = None, store: Any = None) -> None:
        self.stage, self.info, self.train_set, self.plan = stage, info, train_set, plan
        # a batch on the device with what the stage adds (its auxiliary models' inputs)
        self.prepare: Callable[[Batch], Batch] = prepare or (lambda batch: batch.to(self.device))
        self.collate = collate  # the dataset's registered collate
        self._checked: set[str] = set()  # roles whose outputs passed the tap checks
        self.init_left_out: list[str] | None = None  # weights of init_weights that did not fit (strict: false)
        self._last_taps: dict[int, dict[str, Any]] = {}  # per term, detached, for its update()
        self._step = 0  # the step being taken (loss-weight warm-ups read it)
        self.kept: Callable[[], str] = lambda: "no checkpoint had been written yet (a new run starts from step 0)"
        self.own_optimizers: list[torch.optim.Optimizer | None] = []
        self.world, self.device = world, device  # the processes of a multi-process run (one by default)
        spec = stage.spec.train
        self._check_world(len(train_set), spec.batch_size)
        self.student = build_model(stage.student, info)
        if init_weights is not None:  # start from other weights (a resumed run then loads last.pt over them)
            weights, strict, source = init_weights
            self.init_left_out = load_weights(self.student, weights, strict, source)
        self.student = sync_batchnorm(self.student, world, self.device).to(self.device)
        self.task = nn.ModuleList(t.cls(t.params) for t in stage.task_losses).to(self.device)
        self.objectives = nn.ModuleList(o.cls(o.params) for o in stage.distill).to(self.device)
        self.teacher = teacher
        self.store = store  # the teacher's stored outputs (teacher.store), read instead of running it
        if store is not None:  # read with each batch, by the loader's workers where it has them
            from distilkit.engine.store.teacher_outputs import WithTeacherOutputs

            self.collate = WithTeacherOutputs(collate, store)
        self.ema: EmaTeacher | None = None  # the stage is its own teacher (``teacher: {ema: ...}``)
        if stage.ema is not None and stage.distill:
            assert stage.teacher is not None
            self.ema = EmaTeacher(stage.teacher, info, self.student, stage.ema, self.device)
            self.teacher = self.ema.model
        if self.teacher is not None and stage.spec.teacher is not None:  # ``teacher.mode`` (an EMA's: ``ema.mode``)
            self.teacher = apply_mode(self.teacher, stage.spec.teacher.mode, world, device)
            if self.ema is not None:
                self.ema.model = self.teacher
        # per objective: the projection of its student tap (nn.Identity where it has none)
        self.connectors = nn.ModuleList(nn.Identity() for _ in stage.distill)
        self.steps_per_epoch = plan.steps_per_epoch
        for term in self.terms:  # bound first: a term's statistics follow the data's class table
            term.module.bind(self._context())
            term.module.prepare(train_set)
        self._setup_terms()
        own = {id(t.module) for t, o in zip(self.terms, self.own_optimizers) if o is not None}  # train themselves
        freeze(self.stage, [(n, p) for n, p in self._named_parameters() if id(p) not in
                            {id(q) for t in self.terms if id(t.module) in own for q in t.module.parameters()}])
        self.trainable = [p for m in (self.student, *[t.module for t in self.terms if id(t.module) not in own],
                                      self.connectors) for p in m.parameters() if p.requires_grad]
        self.optimizer = self._optimizer(param_groups(self.stage, self.named_trainables()))
        self.scaler = torch.amp.GradScaler(self.device.type, enabled=spec.precision == "fp16")
        self.total_steps = spec.steps if spec.steps is not None else spec.epochs * self.steps_per_epoch
        self.rank_rng(0)

    def first_batch(self) -> Batch:
        """Batch 0 of this process, on the device, prepared as every batch is."""
        return self.prepare(self.plan.batch(self.train_set, self.collate, 0))

    # -- state -------------------------------------------------------------------------------
    def state(self, full: bool = True) -> dict[str, Any]:
        """What a checkpoint holds of the optimisation: the student (with the adapter's name and parameters), the
        terms and connectors, and (``full``: ``last.pt``, to resume) the optimizers and the gradient scaler."""
        out: dict[str, Any] = {
            "student": self.student.state_dict(), "task_losses": self.task.state_dict(),
            "objectives": self.objectives.state_dict(), "connectors": self.connectors.state_dict(),
            "adapter": self.stage.student.adapter, "adapter_params": self.stage.student.params.model_dump(mode="json"),
        }
        if full:
            if self.ema is not None:
                out["ema_teacher"] = self.ema.state_dict()
            elif self.teacher is not None and self.teacher.training:  # its BatchNorm statistics move (teacher_mode)
                out["teacher_buffers"] = teacher_buffers(self.teacher)
            out["optimizer"] = self.optimizer.state_dict()
            out["term_optimizers"] = [o.state_dict() if o is not None else {} for o in self.own_optimizers]
            if self.scaler.is_enabled():
                out["scaler"] = self.scaler.state_dict()
        return out

    def load_state(self, ckpt: dict[str, Any]) -> None:
        """Everything :meth:`state` saved, back in place (a resumed run)."""
        self.student.load_state_dict(ckpt["student"])
        self.task.load_state_dict(ckpt["task_losses"])
        self.objectives.load_state_dict(ckpt["objectives"])
        self.connectors.load_state_dict(ckpt.get("connectors", {}))
        if self.ema is not None:
            if "ema_teacher" not in ckpt:
                raise DistilkitError(f"stage {self.stage.name!r}: the checkpoint to resume from has no EMA teacher "
                                     "(it was written by a run without `teacher: {ema: ...}`)")
            self.ema.load_state_dict(ckpt["ema_teacher"])
        elif self.teacher is not None and self.teacher.training:
            if "teacher_buffers" not in ckpt:
                raise DistilkitError(f"stage {self.stage.name!r}: the checkpoint to resume from has no teacher buffers "
                                     "(it was written by a run whose teacher was not in `mode: train`)")
            load_teacher_buffers(self.teacher, ckpt["teacher_buffers"], f"stage {self.stage.name!r}")
        for opt, state in zip(self.own_optimizers, ckpt.get("term_optimizers", [])):
            if opt is not None and state:
                opt.load_state_dict(state)
        self.optimizer.load_state_dict(ckpt["optimizer"])
        if self.scaler.is_enabled() and ckpt.get("scaler"):
            self.scaler.load_state_dict(ckpt["scaler"])

    def rank_rng(self, step: int) -> None:
        """Multi-process: each process its own random stream from here on (noise levels, dropout), the same ones
        again when the run resumes at ``step`` — models and connectors were built above from the common seed."""
        if self.world.distributed:
            torch.manual_seed((self.plan.seed * 1_000_003 + step) * 1_009 + self.world.rank)

    def _check_world(self, n: int, batch_size: int) -> None:
        """Every process gets samples of every global batch (the last one of an epoch included)."""
        size = self.world.size
        if size > 1 and (batch_size % size or 0 < n % batch_size < size):
            raise DistilkitError(f"stage {self.stage.name!r}: train.batch_size {batch_size} is the global batch of "
                                 f"{size} processes; it must be a multiple of {size} (and the last batch of an epoch "
                                 f"of {n} samples, {n % batch_size}, at least {size})")

    def _autocast(self) -> Any:
        """The models' forward precision (``train.precision``); a no-op context for fp32."""
        from distilkit.engine.train.precision import autocast

        return autocast(self.device, self.stage.spec.train.precision)

    def _named_parameters(self) -> list[tuple[str, nn.Parameter]]:
        """Every parameter of the student, the terms and the connectors by qualified name: ``student.*``,
        ``task.<term>.*``, ``distill.<objective>.*``, ``connector.<objective>.*``."""
        named = [(f"student.{n}", p) for n, p in self.student.named_parameters()]
        for prefix, specs, mods in (("task", self.stage.task_losses, self.task),
                                    ("distill", self.stage.distill, self.objectives),
                                    ("connector", self.stage.distill, self.connectors)):
            for spec, mod in zip(specs, mods):
                named += [(f"{prefix}.{spec.key}.{n}", p) for n, p in mod.named_parameters()]
        return named

    def named_trainables(self) -> list[tuple[str, nn.Parameter]]:
        """Trainable parameters by qualified name (see :meth:`_named_parameters`)."""
        mine = {id(p) for p in self.trainable}
        return [(n, p) for n, p in self._named_parameters() if p.requires_grad and id(p) in mine]

    def _optimizer(self, params: list[dict[str, Any]]) -> torch.optim.Optimizer:
        """The registered optimizer (``optimizer.name``) over the groups; each group keeps its ``base_lr``, which
        the schedule scales step by step (:meth:`_set_lr`)."""
        from distilkit.registry import OPTIMIZERS

        optimizer = OPTIMIZERS.get(self.stage.spec.optimizer.name)(params, self.stage.spec.optimizer)
        for group in optimizer.param_groups:
            group["base_lr"] = group["lr"]
        return optimizer

    def _set_lr(self, step: int) -> float:
        """Every group's learning rate at 0-based ``step``: its base rate times the schedule's factor."""
        schedule = self.stage.spec.optimizer.schedule
        factor = lr_factor(schedule, self.stage.schedule or _no_params(), step, self.total_steps)
        for group in self.optimizer.param_groups:
            group["lr"] = group.get("base_lr", group["lr"]) * factor
        return self.stage.spec.optimizer.lr * factor

    # -- gradients ---------------------------------------------------------------------------
    def _grad_norm(self, clip: float | None) -> Tensor:
        """Total gradient norm of the trainables (clipping them to ``clip`` when it is set)."""
        grads = [p for p in self.trainable if p.grad is not None]
        if not grads:
            return torch.zeros(())
        if clip is not None:
            return torch.nn.utils.clip_grad_norm_(grads, clip)
        return torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(p.grad.detach()) for p in grads]))

    def _blame(self, batch: Batch) -> str:
        """Name the term(s) whose gradient is not finite, by one backward pass per term on the same batch."""
        try:
            with torch.random.fork_rng(devices=[]):
                terms = self.loss_terms(batch)
                params = [p for p in self.trainable]
                bad = []
                for name, value in terms.items():
                    if not value.requires_grad:
                        continue
                    grads = torch.autograd.grad(value, params, retain_graph=True, allow_unused=True)
                    if any(g is not None and not bool(torch.isfinite(g).all()) for g in grads):
                        bad.append(name)
        except Exception as exc:  # diagnosis must never hide the original problem
            return f"the term could not be told: {type(exc).__name__}"
        if not bad:
            return "no single term's gradient is non-finite on its own; check the learning rate"
        return f"non-finite gradient from term(s) {', '.join(bad)}"

    @property
    def terms(self) -> list[StageTerm]:
        """Every term of the stage loss, task losses first, with its logged name and connector."""
        out = [StageTerm(spec.key, "task loss", spec, mod, None) for spec, mod in zip(self.stage.task_losses, self.task)]
        return out + [StageTerm(f"kd_{spec.key}", "objective", spec, mod, con)
                      for spec, mod, con in zip(self.stage.distill, self.objectives, self.connectors)]

    @staticmethod
    def _roles(term: StageTerm, s_out: dict[str, Any], t_out: dict[str, Any], batch: Batch,
               partial: bool = False, float32: bool = False) -> dict[str, Any]:
        """The value of each of a term's roles: a student or teacher tap, or a batch field (``partial``: only the
        taps the outputs hold — the setup pass runs the student in eval mode, where some adapters return less;
        ``float32``: the taps of reduced-precision models in float32, before the term's connector sees them)."""
        cls = term.spec.cls
        taps = {role: (t_out if role in cls.TEACHER_ROLES else s_out)[tap] for role, tap in term.spec.taps.items()
                if not partial or tap in (t_out if role in cls.TEACHER_ROLES else s_out)}
        if float32:
            taps = {role: to_float32(v) for role, v in taps.items()}
        taps.update({role: batch.field(name) for role, name in term.spec.fields.items()})
        if term.connector is not None and term.spec.connector is not None and "student" in taps:
            taps["student"] = term.connector(taps["student"], batch.size)
        return taps

    @property
    def _teacher_outputs_needed(self) -> bool:
        """Whether some term reads a teacher tap (else the teacher runs only when a term calls it)."""
        return any(role in t.spec.cls.TEACHER_ROLES for t in self.terms for role in t.spec.taps)

    def _teacher_outputs(self, batch: Batch) -> dict[str, Any]:
        if not self._teacher_outputs_needed:
            return {}
        if self.store is not None:  # each sample's rows under the draw it is seen under (teacher_store)
            from distilkit.engine.store.teacher_outputs import to_device

            read = batch.meta.get("teacher_outputs")  # by the loader (WithTeacherOutputs), else here
            read = self.store.of(batch, self.device) if read is None else read
            return {k: to_device(v, self.device) for k, v in read.items()}
        assert self.teacher is not None
        other = batch.meta.get("teacher_batch")  # control: shuffled, live: the partners' batch (controls.WithPartner)
        with torch.no_grad(), self._autocast():
            t_out = self.teacher(batch if other is None else self.prepare(other))
        self._check_outputs(self.teacher, t_out, "teacher")
        return t_out

    def _setup_terms(self) -> None:
        """Size the terms' own layers and connectors from one real batch (before the optimizer exists)."""
        needs_batch = len(self.objectives) > 0 or any(type(t.module).setup is not Term.setup for t in self.terms)
        if needs_batch:
            batch = self.first_batch()
            was = self.student.training
            self.student.eval()
            with torch.no_grad(), evaluating(self.teacher):  # a train-mode teacher's statistics move in steps only
                s_out, t_out = self.student(batch), self._teacher_outputs(batch)
                self._check_outputs(self.student, s_out, "student", strict=False)
                for j, spec in enumerate(self.stage.distill):  # a connector maps the student tap to the teacher's
                    if spec.connector is not None:
                        # on the device at once: the terms' setup below already runs the student tap through it
                        self.connectors[j] = Connector(spec.connector, s_out[spec.taps["student"]],
                                                       t_out[spec.taps["teacher"]]).to(self.device)
                for term in self.terms:  # bound first: setup may build from the teacher (an auxiliary copy)
                    term.module.bind(self._context())
                    term.module.setup(self._roles(term, s_out, t_out, batch, partial=True), batch)
            self.student.train(was)
        self.task.to(self.device)
        self.objectives.to(self.device)
        self.connectors.to(self.device)
        for term in self.terms:
            term.module.bind(self._context())
        self.own_optimizers = [term.module.own_optimizer() for term in self.terms]

    def _context(self) -> TermContext:
        return TermContext(self.student, self.teacher, self.device, sync=self.world.average_gradients, info=self.info)

    def _check_outputs(self, model: Adapter, outputs: dict[str, Any], role: str, strict: bool = True) -> None:
        """Every declared tap the forward returned is of its kind, and every tap a term reads is there (checked
        once, on the first batch). An adapter may leave out taps no term reads (LiDiff samples its prediction
        only in evaluation)."""
        if role in self._checked:
            return
        from distilkit.errors import TapError
        # strict=False (the setup pass, in eval mode): kinds of what is there; the first training step checks the rest

        adapter = type(model).__name__
        read = {tap for t in self.terms for r, tap in t.spec.taps.items()
                if (r in t.spec.cls.TEACHER_ROLES) == (role == "teacher")}
        for tap, kind in model.tap_kinds.items():
            if tap not in outputs:
                if tap in read and strict:
                    raise TapError(f"stage {self.stage.name!r}: the {role} ({adapter}) declares tap {tap!r}, which a "
                                   f"term reads, but its forward did not return it (returned: "
                                   f"{', '.join(map(str, outputs))})")
                continue
            check_tap(outputs[tap], kind, f"stage {self.stage.name!r}, {role} ({adapter}) tap {tap!r}")
        if strict:
            self._checked.add(role)

    def loss_terms(self, batch: Batch) -> dict[str, Tensor]:
        """The weighted value of every term on ``batch`` (the teacher runs when a term reads its taps)."""
        with self._autocast():
            s_out = self.student(batch)
        self._check_outputs(self.student, s_out, "student")
        return self.term_values(s_out, self._teacher_outputs(batch) if len(self.objectives) else {}, batch)

    def term_values(self, s_out: dict[str, Any], t_out: dict[str, Any], batch: Batch) -> dict[str, Tensor]:
        """The weighted value of every term given the student's and the teacher's outputs on ``batch``."""
        terms: dict[str, Tensor] = {}
        for i, term in enumerate(self.terms):
            # terms (and their connectors) in float32, outside autocast
            taps = self._roles(term, s_out, t_out, batch, float32=self.stage.spec.train.precision != "fp32")
            self._last_taps[i] = {role: v.detach() if hasattr(v, "detach") else v for role, v in taps.items()}
            try:
                weight = term.spec.weight * weight_factor(term.spec.warmup_steps, self._step)
                terms[term.key] = weight * term.module.compute(taps, batch)
            except DistilkitError as exc:  # one line naming where: stage and term
                where = f"stage {self.stage.name!r}, {term.what} {term.spec.key!r}: {exc}"
                try:
                    err = type(exc)(where)
                except TypeError:
                    err = DistilkitError(where)
                raise err from None
        return terms

    def train_step(self, batch: Batch, step: int) -> dict[str, float]:
        """One optimizer step of the student (then the objectives' own updates); returns the values to log."""
        self._step = step
        lr = self._set_lr(step)
        momentum = self.ema.update(step) if self.ema is not None else None  # before the forward, as HASSC's release
        terms = self.loss_terms(batch)
        loss = torch.stack(list(terms.values())).sum()
        bad = [k for k, v in terms.items() if not torch.isfinite(v)]
        if self.world.any(bool(bad)):  # all processes stop together
            bad = bad or ["(in another process)"]
            raise NonFiniteLossError(
                f"stage {self.stage.name!r}, step {step + 1}: loss term(s) {', '.join(bad)} became "
                f"{', '.join(str(float(terms[k].detach())) if k in terms else 'non-finite' for k in bad)}; training stopped, "
                f"{self.kept()}. Lower the learning rate or the term's weight.")
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(loss).backward()
        self.world.average_gradients(self.trainable)  # multi-process: every process takes the same step
        self.scaler.unscale_(self.optimizer)
        grad_norm = self._grad_norm(self.stage.spec.train.grad_clip)
        if not torch.isfinite(grad_norm) and not self.scaler.is_enabled():  # fp16: the scaler skips the step
            raise NonFiniteLossError(
                f"stage {self.stage.name!r}, step {step + 1}: the gradient became {float(grad_norm)} "
                f"({self._blame(batch)}) although every loss term was finite; no weight was updated, {self.kept()}. "
                "Lower the learning rate or the term's weight.")
        self.scaler.step(self.optimizer)
        self.scaler.update()
        extra: dict[str, float] = {}
        for i, term in enumerate(self.terms):
            extra.update(term.module.update(step, batch, self._last_taps.get(i, {})))
        if momentum is not None:
            extra["ema_momentum"] = momentum
        return {"loss": float(loss.detach()), **{k: float(v.detach()) for k, v in terms.items()}, "lr": lr, **extra}

def _no_params() -> Any:
    from distilkit.engine.train.optim import NoParams

    return NoParams()
