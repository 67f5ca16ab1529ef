"""LiDiff's cards (torch-free): the diffusion adapter ``lidiff``, its refinement ``lidiff-refine`` and its task loss
``lidiff`` — their parameters, taps, roles and what ``validate`` asks of them; the implementations are
:mod:`distilkit_adapters.lidiff.adapter`'s, :mod:`~distilkit_adapters.lidiff.refine`'s and
:mod:`~distilkit_adapters.lidiff.loss`'s."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from distilkit.cards.base import AdapterCard, TermCard
from distilkit.registry import ADAPTERS, TASK_LOSSES
from distilkit_adapters._cards import fields_of_one_size


class LiDiffParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    size: Literal["tiny", "paper"] = Field(
        "tiny", description="tiny: the CPU stand-in (a per-point MLP denoiser: every completed point an independent "
                            "sample; the four fields below); paper: LiDiff's MinkUNetDiff and scan encoder on 5 cm "
                            "sparse voxels (distilkit.sparse), which loads the release's diff_net.ckpt")
    channels: int = Field(64, ge=4, description="tiny: width of the denoiser's point MLPs")
    blocks: int = Field(3, ge=1, description="tiny: modulated residual blocks")
    k_scan: int = Field(8, ge=1, description="tiny: scan neighbours of the scan encoder's local descriptor")
    k_cond: int = Field(4, ge=1, description="tiny: nearest scan points that condition each noisy point")
    diffusion_steps: int = Field(1000, ge=2, description="T (LiDiff: 1000)")
    beta_start: float = Field(3.5e-5, gt=0)
    beta_end: float = Field(0.007, gt=0)
    duplicate: int = Field(10, ge=1, description="K: the scan is duplicated K times as the start of sampling "
                                                "(LiDiff: 10 = scene points / scan points)")
    sample_steps: int = Field(50, ge=1, description="sampler steps at evaluation = network evaluations (LiDiff: 50; "
                                                    "ScoreLiDAR's student: 8)")
    sampler: Literal["ddim", "dpm-solver++"] = Field(
        "ddim", description="ddim: deterministic DDIM of the local-noise process (consistent with its training); "
                            "dpm-solver++: what LiDiff runs, diffusers 0.18's second-order SDE DPM-Solver++ on the "
                            "offset x - x_init (parity with released teachers)")
    guidance: float = Field(1.0, ge=0, description="classifier-free guidance weight when sampling (LiDiff: 6.0, "
                                                   "ScoreLiDAR: 3.5; 1 = the conditional prediction alone)")
    postprocess: bool = Field(True, description="LiDiff's post-processing of the evaluated completion: keep points "
                                                "within 50 m whose height lies in (mean - 2 std, max) of the scan's")
    uncond_prob: float = Field(0.1, ge=0, le=1, description="probability that the condition is dropped (LiDiff: 0.1)")
    uncond_per: Literal["batch", "scene"] = Field(
        "batch", description="batch: one draw per training batch drops every scene's condition (LiDiff's "
                             "training_step); scene: one draw per scene. A batch of one scene always keeps it (LiDiff)")
    generate_steps: int = Field(0, ge=0, description="0: training denoises noised scenes (LiDiff); n > 0: training "
                                                     "generates ``samples`` in n sampler steps with their gradient "
                                                     "(a few-step student, ScoreLiDAR: 1)")
    freeze_encoder: bool | None = Field(None, description="keep the scan encoder's weights fixed (default: frozen for "
                                                          "a few-step student, generate_steps > 0, as ScoreLiDAR's code "
                                                          "keeps the teacher's encoder; trained otherwise)")

    @model_validator(mode="after")
    def _one_size(self) -> "LiDiffParams":
        fields_of_one_size(self, {"tiny": ("channels", "blocks", "k_scan", "k_cond")})
        return self


class LiDiffCard(AdapterCard):
    """LiDiff's declarations (the adapter: :class:`distilkit_adapters.lidiff.adapter.LiDiffAdapter`); the
    capabilities distillation terms call on it: ``predict_noise`` (a teacher's) and ``generate`` (a few-step
    student's)."""

    Params = LiDiffParams
    INPUTS = frozenset({"scan", "scan_lengths", "scene", "scene_lengths"})  # training noises the scene
    TAPS = {"eps_pred": "points", "eps": "points", "samples": "points", "start_noise": "points", "completion": "points"}
    PREDICTION_TAP = "completion"
    DEFAULT_TASK_LOSSES = [{"name": "lidiff", "taps": {"student": "eps_pred", "noise": "eps"}}]
    VERSION = 3  # 2: n sampler steps are n network evaluations (none at t = 0); 3: the condition dropped per batch
    NETWORKS = {"tiny": "CPU stand-in: a per-point MLP denoiser (every completed point an independent sample)",
                "paper": "the paper's network: MinkUNetDiff and the scan encoder on 5 cm sparse voxels (loads "
                         "diff_net.ckpt)"}
    CAPABILITIES = frozenset({"predict_noise", "generate"})

    @classmethod
    def sparse(cls, params: BaseModel) -> bool:
        """The paper's network (``size: paper``) runs sparse convolutions (distilkit.sparse); the stand-in none."""
        return getattr(params, "size") == "paper"

    @classmethod
    def describe(cls, params: BaseModel) -> str:
        n = int(getattr(params, "sample_steps"))
        return f"{n} step{'s' if n != 1 else ''}" + (", paper size" if getattr(params, "size") == "paper" else "")


class RefineParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    size: Literal["tiny", "paper"] = Field(
        "tiny", description="tiny: per-point MLPs with an edge descriptor (the CPU stand-in; channels, k, chunk); "
                            "paper: LiDiff's refinement MinkUNet on 5 cm sparse voxels, which loads refine_net.ckpt")
    channels: int = Field(32, ge=4, description="tiny: width of the point MLPs")
    k: int = Field(8, ge=1, description="tiny: neighbours of each point's edge descriptor")
    offsets: int = Field(6, ge=1, description="points predicted per input point (LiDiff: 6)")
    max_offset: float = Field(1.0, gt=0, description="offsets lie in [-max_offset, max_offset] per axis (LiDiff: "
                                                     "tanh, 1 m)")
    chunk: int = Field(32768, ge=1, description="points per chunk of the descriptor (bounds memory, not results)")
    train_on: Literal["jittered-ground-truth", "completions"] = Field(
        "jittered-ground-truth", description="training input: the ground-truth scene with clipped Gaussian jitter "
                                             "(LiDiff's refinement training; default) or an auxiliary LiDiff model's "
                                             "completions (the aux input coarse)")
    jitter_sigma: float = Field(0.2, gt=0, description="jitter standard deviation, metres (LiDiff: 0.2)")
    jitter_clip: float = Field(0.3, gt=0, description="jitter clipped to [-clip, clip] per axis, metres (LiDiff: 0.3)")

    @model_validator(mode="after")
    def _one_size(self) -> "RefineParams":
        fields_of_one_size(self, {"tiny": ("channels", "k", "chunk")})
        return self


class LiDiffRefineCard(AdapterCard):
    """LiDiff's refinement's declarations (the adapter:
    :class:`distilkit_adapters.lidiff.refine.LiDiffRefineAdapter`)."""

    Params = RefineParams
    INPUTS = frozenset({"coarse", "scene", "scene_lengths"})
    TAPS = {"refined": "points", "completion": "points"}
    AUX_INPUTS = {"coarse": "lidiff"}  # a LiDiff stage's completion
    PREDICTION_TAP = "completion"
    DEFAULT_TASK_LOSSES = [{"name": "chamfer", "taps": {"student": "refined"}}]
    VERSION = 2  # 2: trained on jittered ground truth by default (LiDiff)
    NETWORKS = {"tiny": "CPU stand-in: a per-point MLP refiner",
                "paper": "the paper's network: LiDiff's refinement MinkUNet (loads refine_net.ckpt)"}

    @classmethod
    def inputs(cls, params: BaseModel) -> frozenset[str]:
        """``coarse`` (an auxiliary model's completion, refined in evaluation), and the ground-truth ``scene`` when
        training on it."""
        jitter = getattr(params, "train_on") == "jittered-ground-truth"
        return cls.INPUTS if jitter else frozenset({"coarse"})

    @classmethod
    def sparse(cls, params: BaseModel) -> bool:
        """The paper's network (``size: paper``) runs sparse convolutions (distilkit.sparse); the stand-in none."""
        return getattr(params, "size") == "paper"

    @classmethod
    def describe(cls, params: BaseModel) -> str:
        size = ", paper size" if getattr(params, "size") == "paper" else ""
        return f"{getattr(params, 'offsets')}x refinement{size}"


class LiDiffLossParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    reg_weight: float = Field(5.0, ge=0, description="weight of the mean/std regulariser (LiDiff: 5.0)")


class LiDiffLossCard(TermCard):
    """LiDiff's task loss's declarations (the loss: :class:`distilkit_adapters.lidiff.loss.LiDiffLoss`)."""

    Params = LiDiffLossParams
    CONSUMES = {"student": "points", "noise": "points"}


ADAPTERS.declare("lidiff", "distilkit_adapters.lidiff.adapter:LiDiffAdapter", card=LiDiffCard,
                 description="LiDiff: scan-conditioned point diffusion with local noise (pure-PyTorch point denoiser), "
                             "DDIM sampling with any number of steps",
                 paper="Nunes et al., LiDiff, CVPR 2024", consumes=tuple(LiDiffCard.TAPS.values()))
ADAPTERS.declare("lidiff-refine", "distilkit_adapters.lidiff.refine:LiDiffRefineAdapter", card=LiDiffRefineCard,
                 description="LiDiff's refinement: six offsets per point of a diffusion completion (Chamfer-trained on "
                             "jittered ground truth, or on a frozen auxiliary LiDiff model's completions)",
                 paper="Nunes et al., LiDiff, CVPR 2024 (models_refine.py)",
                 consumes=tuple(LiDiffRefineCard.TAPS.values()))
TASK_LOSSES.declare("lidiff", "distilkit_adapters.lidiff.loss:LiDiffLoss", card=LiDiffLossCard,
                    description="LiDiff's denoising MSE + 5 (mean^2 + (std - 1)^2) of the noise",
                    paper="Nunes et al., LiDiff, CVPR 2024; ScoreLiDAR eq. 5", consumes=("points",))
