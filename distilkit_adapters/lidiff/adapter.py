"""How distilkit sees LiDiff: training taps ``eps_pred``/``eps`` (the denoising pair) or, for a few-step student,
``samples`` (generated with their gradient) and the ``start_noise`` they came from, and in evaluation the sampled,
post-processed ``completion``; it offers the capabilities ``alphas_cumprod``, ``predict_noise``, ``sample`` and
``generate`` (the few-step generator from a given noise)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from distilkit.adapter import Adapter
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.structures import PointCloud
from distilkit_adapters.lidiff.card import LiDiffCard, LiDiffParams
from distilkit_adapters.lidiff.model import PointDenoiser, lidiff_alphas_cumprod
from distilkit_adapters.lidiff.sampler import ddim, ddim_timesteps, dpm_timesteps, sde_dpmsolver_pp


class LiDiffAdapter(LiDiffCard, Adapter):
    """LiDiff with its denoising loss (``lidiff`` task loss) and a DDIM sampler of any number of steps. Its choices
    (``CHOICES``): the sampler of few-step students, the per-point denoiser, the condition dropped per batch."""

    CHOICES = (
        Choice("few-step sampler", "DDIM of the local-noise process (`sampler: ddim`): n steps = n network calls, "
                                   "the last returns x0", "ScoreLiDAR §4: the student samples in one step",
               "ScoreLiDAR trains with one SDE-DPM-Solver++ step (diffusers 0.18) and evaluates 8 DPM steps",
               "`sampler: dpm-solver++`"),
        Choice("denoiser", "a per-point MLP conditioned on its nearest scan points: every completed point is an "
                           "independent sample given the scan", "MinkUNet (sparse convolutions): points interact",
               "MinkUNetDiff over 5 cm voxels (minkunet.py)"),
        Choice("condition dropout", "one draw per batch drops every scene's scan (p = uncond_prob); a batch of one "
                                    "keeps it", "classifier-free guidance, 10 % unconditional",
               "models.py: `if torch.rand(1) > uncond_prob or batch size == 1` (per batch)", "`uncond_per: scene`"),
    )

    def __init__(self, params: LiDiffParams, info: DataInfo) -> None:
        super().__init__(params, info)
        if params.size == "paper":
            from distilkit_adapters.lidiff.minkunet import LiDiffNet

            self.net: Any = LiDiffNet()
        else:
            self.net = PointDenoiser(params.channels, params.blocks, params.k_scan, params.k_cond)
        frozen = params.freeze_encoder if params.freeze_encoder is not None else params.generate_steps > 0
        for p in self.net.encoder.parameters():
            p.requires_grad_(not frozen)
        abar = lidiff_alphas_cumprod(params.diffusion_steps, params.beta_start, params.beta_end)
        self.register_buffer("alphas_cumprod", abar.float(), persistent=False)

    @classmethod
    def read_weights(cls, path: str) -> dict[str, Any]:
        """A distilkit checkpoint, or LiDiff's released Lightning checkpoint (``diff_net.ckpt``: ``partial_enc.*`` and
        ``model.*``, MinkowskiEngine kernels) converted to the paper-size network's names and layout."""
        from distilkit_adapters.lidiff.weights import from_lightning

        return from_lightning(super().read_weights(path), ("partial_enc.", "model."))

    # -- the Denoiser capability -------------------------------------------------------------------
    def sigma(self, t: Tensor) -> Tensor:
        """sqrt(1 - abar_t), the local noise scale at integer timesteps t."""
        return (1.0 - self.alphas_cumprod[t]).sqrt()

    def predict_noise(self, x_t: Tensor, t: Tensor, condition: Tensor, guidance: float = 1.0,
                      encoded: tuple[Tensor, Tensor | None] | None = None) -> Tensor:
        """eps_hat (B, M, 3) of noisy points (B, M, 3) at timesteps t (B,), given the scan (B, N, 3); with
        classifier-free guidance eps_u + w (eps_c - eps_u) when ``guidance`` != 1. The unconditional input is LiDiff's
        all-zero scan, given as one point at the origin: N copies of it have the same neighbours and features (the
        same eps_u) but make every nearest-neighbour query degenerate. ``encoded``: :meth:`encode`'s result."""
        enc_c, enc_u = encoded if encoded is not None else (None, None)
        eps = self.net(x_t, t, condition, enc_c)
        if guidance != 1.0:
            eps_u = self.net(x_t, t, self.unconditional(condition), enc_u)
            eps = eps_u + guidance * (eps - eps_u)
        return eps

    @staticmethod
    def unconditional(condition: Tensor) -> Tensor:
        """LiDiff's dropped condition, an all-zero scan, as one point (B, 1, 3)."""
        return condition.new_zeros((condition.shape[0], 1, 3))

    def encode(self, condition: Tensor, unconditional: bool = True) -> tuple[Tensor, Tensor | None]:
        """The scan encoder's features of the scan and (``unconditional``: only guidance needs them) of the
        unconditional input: they depend on neither x_t nor t, so a sampler computes them once. (A one-point
        unconditional scan in a batch of one cannot pass the paper-size encoder's batch norms in training mode:
        ScoreLiDAR's generator samples without guidance, so it never encodes one.)"""
        return (self.net.encoder(condition),
                self.net.encoder(self.unconditional(condition)) if unconditional else None)

    def timesteps(self, steps: int) -> list[int]:
        """The ``steps`` timesteps the sampler evaluates the network at (one each, none at t = 0)."""
        spacing = ddim_timesteps if self.params.sampler == "ddim" else dpm_timesteps
        return spacing(steps, self.params.diffusion_steps)

    def start(self, condition: Tensor, generator: torch.Generator | None = None,
              noise: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """(x_init, x_T): the scan duplicated K times, and it plus N(0, I) noise (LiDiff's start point; ``noise``
        given: that noise)."""
        x_init = condition.repeat(1, self.params.duplicate, 1)
        if noise is None:
            noise = torch.randn(x_init.shape, generator=generator, device=x_init.device, dtype=x_init.dtype)
        elif noise.shape != x_init.shape:
            raise ValueError(f"start noise {tuple(noise.shape)} must match the duplicated scan {tuple(x_init.shape)}")
        return x_init, x_init + noise

    def generate(self, condition: Tensor, noise: Tensor) -> Tensor:
        """The few-step generator of training (``generate_steps``, no guidance) from a given start noise, with its
        gradient (the ``generate`` capability: Distillation-DPO completes one scan from two noises)."""
        return self.sample(condition, steps=self.params.generate_steps or self.params.sample_steps, guidance=1.0,
                           noise=noise)

    def sample(self, condition: Tensor, steps: int | None = None, guidance: float | None = None,
               generator: torch.Generator | None = None, noise: Tensor | None = None) -> Tensor:
        """A completed scene (B, K*N, 3) from the scan (B, N, 3): ``steps`` network evaluations (two each with
        guidance) of the configured sampler (:mod:`distilkit_adapters.lidiff.sampler`)."""
        ts = self.timesteps(steps or self.params.sample_steps)
        w = self.params.guidance if guidance is None else guidance
        x_init, x = self.start(condition, generator, noise)
        b = x.shape[0]
        encoded = self.encode(condition, unconditional=w != 1.0)

        def eps(x_t: Tensor, t: int) -> Tensor:
            tt = torch.full((b,), t, dtype=torch.long, device=x_t.device)
            return self.predict_noise(x_t, tt, condition, w, encoded)

        if self.params.sampler == "ddim":
            return ddim(eps, x, self.sigma(torch.arange(len(self.alphas_cumprod), device=x.device)), ts)
        offset = sde_dpmsolver_pp(lambda o, t: eps(x_init + o, t), x - x_init, self.alphas_cumprod, ts, generator)
        return x_init + offset

    # -- completing a user's scan (``distilkit complete``) ----------------------------------------
    def complete_scan(self, points: Any, *, scan_points: int | None = None, steps: int | None = None,
                      guidance: float | None = None, seed: int = 0) -> tuple[Any, int, int]:
        """A completed scene from a raw scan ((N, 3) numpy), prepared and post-processed as LiDiff does
        (:mod:`distilkit_adapters.lidiff.complete`); also the scan points it was sampled to and the sampler steps."""
        from distilkit_adapters.lidiff.complete import DEFAULT_SCAN_POINTS, prepare_scan

        count = scan_points or DEFAULT_SCAN_POINTS
        prepared = prepare_scan(points, count, seed)
        device = next(self.parameters()).device
        n_steps = steps or int(self.params.sample_steps)
        with torch.no_grad():
            cond = torch.from_numpy(prepared)[None].to(device)
            scene = self.completion(cond, steps=n_steps, guidance=guidance,
                                    generator=torch.Generator(device=device).manual_seed(seed))
        return scene.cloud(0).cpu().numpy(), count, n_steps

    def completion(self, scan: Tensor, scan_lengths: Tensor | None = None, **sample: Any) -> PointCloud:
        """Sampled scenes (``sample``'s keywords: steps, guidance, generator), post-processed as LiDiff's pipeline
        does when ``postprocess`` (:func:`~distilkit_adapters.lidiff.complete.keep_mask`): variable lengths."""
        from distilkit_adapters.lidiff.complete import keep_mask

        x = self.sample(scan, **sample)
        if not self.params.postprocess:
            return PointCloud(x, torch.full((x.shape[0],), x.shape[1], dtype=torch.int64, device=x.device))
        counts = scan_lengths.tolist() if scan_lengths is not None else [scan.shape[1]] * x.shape[0]
        return PointCloud.from_list([x[b][keep_mask(x[b], scan[b, : int(n)])] for b, n in enumerate(counts)])

    # -- forward -----------------------------------------------------------------------------------
    def forward(self, batch: Batch) -> dict[str, Any]:
        scan = batch.inputs["scan"]
        if not self.training:
            return {"completion": self.completion(scan, batch.inputs.get("scan_lengths"))}
        if self.params.generate_steps:  # a few-step generator: its samples, differentiable (ScoreLiDAR's student)
            noise = torch.randn(scan.shape[0], scan.shape[1] * self.params.duplicate, 3, device=scan.device,
                                dtype=scan.dtype)
            x = self.generate(scan, noise)
            lengths = torch.full((x.shape[0],), x.shape[1], dtype=torch.int64, device=x.device)
            return {"samples": PointCloud(x, lengths), "start_noise": PointCloud(noise, lengths)}
        x0, lengths = batch.field("scene"), batch.field("scene_lengths")
        b = x0.shape[0]
        t = torch.randint(0, self.params.diffusion_steps, (b,), device=x0.device)
        eps = torch.randn_like(x0)
        x_t = x0 + self.sigma(t)[:, None, None] * eps
        if b > 1 and self.params.uncond_prob > 0:  # conditional dropout (LiDiff keeps B = 1 conditional)
            draws = 1 if self.params.uncond_per == "batch" else b
            drop = (torch.rand(draws, device=x0.device) < self.params.uncond_prob).expand(b)
            scan = torch.where(drop[:, None, None], torch.zeros_like(scan), scan)
        eps_pred = self.net(x_t, t, scan)
        return {"eps_pred": PointCloud(eps_pred, lengths), "eps": PointCloud(eps, lengths)}


__all__ = ["LiDiffAdapter", "LiDiffParams"]
