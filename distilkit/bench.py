"""``distilkit bench``: forward+backward timings of objectives at realistic 3-D sizes.

Each case times the fast (shipped) form and, where it fits in memory, the naive form of the
paper's formula on the same inputs, side by side in one run. Peak memory is the growth of the
process's peak resident set (Linux ``VmHWM``, reset through ``/proc/self/clear_refs``) on the
CPU, or ``torch.cuda.max_memory_allocated`` on CUDA.
"""

from __future__ import annotations

import gc
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch
from torch import Tensor


@dataclass
class Case:
    objective: str
    size: str
    fast: Callable[[], Tensor]
    naive: Callable[[], Tensor] | None
    inputs: list[Tensor]
    reference: Callable[[], Tensor] | None = None  # float64 value where the naive form does not fit
    same_value: bool = True  # False: the two forms compute different things (a sampler at other step counts)
    note: Callable[[dict[str, Any]], str] | None = None  # a line under the table from the timed row (e.g. GFLOP/s)
    measure: Callable[[], tuple[float, int | None, float]] | None = None  # its own (ms, peak bytes, value)


def _peak_reset(device: torch.device) -> None:
    gc.collect()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        return
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _peak_bytes(device: torch.device, base: int) -> int | None:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) - base
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024 - base
    except OSError:
        return None
    return None


def _rss(device: torch.device) -> int:
    if device.type == "cuda":
        return torch.cuda.memory_allocated(device)
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def time_fb(fn: Callable[[], Tensor], inputs: list[Tensor], device: torch.device, repeat: int) -> tuple[float, int | None, float]:
    """Median milliseconds of forward+backward, peak extra memory in bytes, and the value."""
    def once() -> float:
        for t in inputs:
            t.grad = None
        out = fn()
        if out.requires_grad:  # a case without trainable input (key-point selection) times its forward
            out.backward()
        return float(out.detach())

    value = once()  # warm-up
    times = []
    _peak_reset(device)
    base = _rss(device)
    for _ in range(repeat):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        value = once()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append((time.perf_counter() - t0) * 1000)
    peak = _peak_bytes(device, base)
    times.sort()
    return times[len(times) // 2], peak, value


def naive_dskd(fs: Tensor, ft: Tensor) -> Tensor:
    """SCPNet eq. 1-2 literally, with the two N x N cosine matrices."""
    a = torch.nn.functional.normalize(fs, dim=1)
    b = torch.nn.functional.normalize(ft, dim=1)
    return ((a @ a.T - b @ b.T) ** 2).mean()


def dskd_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses import dskd

    cases = []
    big = 20_000 if quick else 1_000_000
    small = 2_000 if quick else 16_000
    for n, with_naive in ((big, False), (small, True)):
        g = torch.Generator(device="cpu").manual_seed(0)
        fs = torch.randn(n, 32, generator=g).to(device).requires_grad_(True)
        ft = torch.randn(n, 32, generator=g).to(device)
        cases.append(Case("dskd", f"{n:,} × 32", lambda fs=fs, ft=ft: dskd(fs, ft),
                          (lambda fs=fs, ft=ft: naive_dskd(fs, ft)) if with_naive else None, [fs],
                          None if with_naive else (lambda fs=fs, ft=ft: dskd(fs.detach().double(), ft.double()))))
    return cases


def naive_pkt(s: Tensor, t: Tensor, eps: float = 1e-7) -> Tensor:
    """RepDistiller's PKT: full N x N kernels."""
    xs = torch.nan_to_num(s / (s.norm(dim=1, keepdim=True) + eps))
    xt = torch.nan_to_num(t / (t.norm(dim=1, keepdim=True) + eps))
    ks, kt = (xs @ xs.T + 1) / 2, (xt @ xt.T + 1) / 2
    ps, pt = ks / ks.sum(1, keepdim=True), kt / kt.sum(1, keepdim=True)
    return (pt * torch.log((pt + eps) / (ps + eps))).mean()


def pkt_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses import pkt

    n = 2_048 if quick else 16_384
    g = torch.Generator().manual_seed(0)
    fs = torch.randn(n, 32, generator=g).to(device).requires_grad_(True)
    ft = torch.randn(n, 32, generator=g).to(device)
    return [Case("pkt", f"{n:,} sampled voxels × 32", lambda: pkt(fs, ft), lambda: naive_pkt(fs, ft), [fs])]


def _ssc_logits(device: torch.device, quick: bool) -> tuple[Tensor, Tensor, Tensor, Tensor, str]:
    shape = (64, 64, 8) if quick else (256, 256, 32)
    g = torch.Generator().manual_seed(0)
    s = torch.randn(1, 20, *shape, generator=g).to(device).requires_grad_(True)
    t = torch.randn(1, 20, *shape, generator=g).to(device)
    occupied = (torch.rand(1, *shape, generator=g) < 0.10).to(device)
    labels = torch.randint(1, 20, (1, *shape), generator=g).to(device) * (torch.rand(1, *shape, generator=g) < 0.3).to(device)
    return s, t, occupied, labels, f"1 × 20 × {' × '.join(map(str, shape))}"


def naive_kd(s: Tensor, t: Tensor, mask: Tensor) -> Tensor:
    """KD as usually written: softmax maps, elementwise KL, mean over the selected voxels."""
    ps, pt = torch.softmax(s, 1), torch.softmax(t, 1)
    kl = (pt * (torch.log(pt) - torch.log(ps))).sum(1)
    return kl[mask].mean()


def kd_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses import kd

    s, t, occupied, _, size = _ssc_logits(device, quick)
    valid = torch.ones_like(occupied)
    return [Case("kd", size, lambda: kd(s, t, 1.0, valid), lambda: naive_kd(s, t, valid), [s])]


def naive_rgo2d(s: Tensor, t: Tensor, labels: Tensor, mask: Tensor) -> Tensor:
    """The authors' broadcast form (seed_code.md §2.2): N x K x C masked products, unique classes per region."""
    from distilkit.losses.logit import pearson_rows
    from distilkit.losses.rgo2d import range_regions

    total = s.sum() * 0
    for w, reg in zip((0.06, 0.15, 0.20), range_regions(tuple(s.shape[2:]), "boxes", s.device)):
        m = (mask[0] & reg).reshape(-1)
        ys, yt, lab = s[0].flatten(1).T[m], t[0].flatten(1).T[m], labels[0].reshape(-1)[m]
        u = torch.unique(lab)
        u = u[u != 0]
        if u.numel() == 0:
            continue
        member = (lab[:, None] == u[None, :]).to(ys.dtype)
        gs = (ys[:, None, :] * member[:, :, None]).sum(0) / (member.sum(0)[:, None] + 1e-8)
        gt = (yt[:, None, :] * member[:, :, None]).sum(0) / (member.sum(0)[:, None] + 1e-8)
        ps, pt = gs.softmax(1), gt.softmax(1)
        glob = 2.625 * (1 - pearson_rows(ps, pt).mean()) + 0.375 * (1 - pearson_rows(ps.T, pt.T).mean())
        a_s = torch.nn.functional.cosine_similarity(ys[:, None] + 1e-8, gs[None] + 1e-8, dim=-1)
        a_t = torch.nn.functional.cosine_similarity(yt[:, None] + 1e-8, gt[None] + 1e-8, dim=-1)
        total = total + w * (glob + ((a_s - a_t) ** 2).mean())
    return total


def rgo2d_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses import rgo2d

    s, t, occupied, labels, size = _ssc_logits(device, quick)
    return [Case("rgo2d", size + ", 10 % occupied", lambda: rgo2d(s, t, labels, occupied),
                 lambda: naive_rgo2d(s, t, labels, occupied), [s])]


def naive_nst(s: Tensor, t: Tensor) -> Tensor:
    """RepDistiller's NST: broadcast polynomial kernel over (B, C, C, S)."""
    s = torch.nn.functional.normalize(s.flatten(2), dim=2)
    t = torch.nn.functional.normalize(t.flatten(2), dim=2)

    def poly(a: Tensor, b: Tensor) -> Tensor:
        return (a.unsqueeze(1) * b.unsqueeze(2)).sum(-1).pow(2)

    return poly(t, t).mean() + poly(s, s).mean() - 2 * poly(s, t).mean()


def nst_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses import nst

    cases = []
    sizes = [((32, 32, 4), False), ((16, 16, 4), True)] if quick else [((128, 128, 16), False), ((32, 32, 8), True)]
    for shape, with_naive in sizes:
        g = torch.Generator().manual_seed(0)
        fs = torch.randn(1, 128, *shape, generator=g).to(device).requires_grad_(True)
        ft = torch.randn(1, 128, *shape, generator=g).to(device)
        cases.append(Case("nst", f"1 × 128 × {' × '.join(map(str, shape))}", lambda fs=fs, ft=ft: nst(fs, ft),
                          (lambda fs=fs, ft=ft: naive_nst(fs, ft)) if with_naive else None, [fs]))
    return cases


def _street(m: int, seed: int, device: torch.device) -> Tensor:
    """A LiDAR-like scene of ``m`` points: a ground plane, walls and poles within 50 m (metres)."""
    g = torch.Generator().manual_seed(seed)
    part = m // 3
    ground = torch.cat([torch.rand(part, 2, generator=g) * 100 - 50, torch.randn(part, 1, generator=g) * 0.02 - 1.7], 1)
    wall = torch.cat([torch.rand(part, 1, generator=g) * 100 - 50, 8 + torch.randn(part, 1, generator=g) * 0.05,
                      torch.rand(part, 1, generator=g) * 4 - 1.7], 1)
    rest = m - 2 * part
    centres = (torch.rand(rest // 50 + 1, 2, generator=g) * 80 - 40).repeat_interleave(50, 0)[:rest]
    poles = torch.cat([centres + torch.randn(rest, 2, generator=g) * 0.1, torch.rand(rest, 1, generator=g) * 5 - 1.7], 1)
    return torch.cat([ground, wall, poles]).to(device)


def released_keypoints(points: Tensor, sample: Tensor, k: int, keep: int) -> Tensor:
    """ScoreLiDAR's released key points: a full distance matrix of the sample, argsort, a Python loop of
    eigen-decompositions (seed_code.md §3.5)."""
    p = points[sample]
    nbr = torch.argsort(torch.cdist(p, p), dim=1)[:, 1:k + 1]
    curv = []
    for i in range(p.shape[0]):
        c = p[nbr[i]] - p[nbr[i]].mean(0)
        lam = torch.linalg.eigvalsh(c.T @ c / k)
        curv.append(lam[0] / lam.sum())
    return sample[torch.topk(torch.stack(curv), keep).indices]


def naive_structural(gen: Tensor, gt: Tensor, key: Tensor) -> Tensor:
    """Eq. 12 and 16 literally: a full generated x ground-truth distance matrix for the nearest points, and
    the key points' distance matrices from (n, n, 3) differences."""
    nn_sq = torch.cdist(gen, gt).min(dim=1).values ** 2
    k = gt[key]
    matched = gen[torch.cdist(k, gen).argmin(dim=1)]
    d_t = (k[:, None] - k[None]).norm(dim=-1)
    d_g = (matched[:, None] - matched[None]).norm(dim=-1)
    return 0.5 * nn_sq.mean() + 0.01 * ((d_t - d_g) ** 2).mean()


def structural_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses.structural import curvature, select_keypoints, structural

    big, small = (18_000, 6_000) if quick else (180_000, 30_000)
    cases = []
    for m, with_naive in ((big, False), (small, True)):
        pts = _street(m, 0, device)
        n = round(m * 0.1)
        keep = round(n / 3)

        def fast(pts: Tensor = pts) -> Tensor:
            key = select_keypoints(pts, generator=torch.Generator().manual_seed(0))
            return curvature(pts[key.sort().values], k=min(180, len(key) - 1)).double().sum()

        def naive(pts: Tensor = pts, n: int = n, keep: int = keep) -> Tensor:
            sample = torch.randperm(pts.shape[0], generator=torch.Generator().manual_seed(0))[:n].to(pts.device)
            key = released_keypoints(pts, sample, 180, keep)
            return curvature(pts[key.sort().values], k=min(180, len(key) - 1)).double().sum()

        cases.append(Case("structural key points", f"{m:,} pts → {n:,} sampled → {keep:,} (k = 180)", fast,
                          naive if with_naive else None, []))
    for m, with_naive in ((big, False), ((6_000 if quick else 18_000), True)):
        gt = _street(m, 1, device)
        gen = (gt[torch.randperm(m, generator=torch.Generator().manual_seed(2))] +
               0.05 * torch.randn(m, 3, generator=torch.Generator().manual_seed(3)).to(device)).requires_grad_(True)
        key = select_keypoints(gt, generator=torch.Generator().manual_seed(0))
        cases.append(Case("structural step", f"{m:,} generated vs {m:,} GT, {len(key):,} key pts",
                          lambda gen=gen, gt=gt, key=key: structural(gen, gt, key),
                          (lambda gen=gen, gt=gt, key=key: naive_structural(gen, gt, key)) if with_naive else None,
                          [gen], None if with_naive else
                          (lambda gen=gen, gt=gt, key=key: structural(gen.detach().double(), gt.double(), key))))
    return cases


def sampler_cases(device: torch.device, quick: bool) -> list[Case]:
    """ScoreLiDAR's claim (Table 4): the distilled student samples in 8 steps what the LiDiff teacher samples in 50 —
    the same denoiser, timed side by side ('fast' = 8 steps, 'naive' = 50). The model is built through the adapter
    registry at recipes/scorelidar.yaml's size (weights random: the time does not depend on them)."""
    cases = []
    for scan in ((64,) if quick else (256, 1024)):
        model, _ = _lidiff_models(device, scan)
        points = _street(scan, 0, device)[None]

        def run(steps: int, model=model, points=points) -> Tensor:
            with torch.no_grad():
                return model.sample(points, steps=steps, generator=torch.Generator().manual_seed(0)).sum()

        cases.append(Case("sampler 8 vs 50 steps", f"{scan:,}-pt scan → {10 * scan:,} pts", lambda run=run: run(8),
                          lambda run=run: run(50), [], same_value=False))
    return cases


def _lidiff_models(device: torch.device, scan: int) -> tuple[Any, Any]:
    """recipes/scorelidar.yaml's LiDiff denoiser and refiner, built through the adapter registry (random weights: the
    time does not depend on them)."""
    from distilkit.data.params import SceneParams
    from distilkit.data.scenes import scenes_info
    from distilkit.registry import ADAPTERS

    info = scenes_info(SceneParams(scan_points=scan, scene_points=10 * scan))
    with torch.random.fork_rng(devices=[]):
        lidiff, refine = ADAPTERS.get("lidiff"), ADAPTERS.get("lidiff-refine")
        model = lidiff(lidiff.Params(channels=32, blocks=2, duplicate=10, sample_steps=8), info).to(device).eval()
        refiner = refine(refine.Params(channels=32), info).to(device).eval()
    return model, refiner


def guidance_cases(device: torch.device, quick: bool) -> list[Case]:
    """The cost of classifier-free guidance (LiDiff 6.0, ScoreLiDAR 3.5): its second, unconditional network call per
    step, 8 steps with guidance 1 ('fast': one call) and 3.5 ('naive': two calls), per scene."""
    cases = []
    for scan in ((64,) if quick else (256, 1024)):
        model, _ = _lidiff_models(device, scan)
        points = _street(scan, 0, device)[None]

        def run(w: float, model=model, points=points) -> Tensor:
            with torch.no_grad():
                return model.sample(points, steps=8, guidance=w, generator=torch.Generator().manual_seed(0)).sum()

        cases.append(Case("guidance 1 vs 3.5, 8 steps", f"{scan:,}-pt scan → {10 * scan:,} pts",
                          lambda run=run: run(1.0), lambda run=run: run(3.5), [], same_value=False))
    return cases


def complete_cases(device: torch.device, quick: bool) -> list[Case]:
    """``distilkit complete`` on a scan the size of an HDL-64E sweep (125,000 points; 20,000 with --quick): LiDAR-frame
    preparation and farthest-point sampling to LiDiff's 18,000 scan points (1,024 quick), 8 DPM-free DDIM steps at
    guidance 3.5 into 10x the points, post-processing; 'fast' without refinement, 'naive' with the 6x refinement
    network on top (the columns compare the two: the refinement's time and memory)."""
    n, scan = (20_000, 1024) if quick else (125_000, 18_000)
    model, refiner = _lidiff_models(device, scan)
    raw = _street(n, 1, torch.device("cpu")).numpy()

    def run(refine: bool) -> Tensor:
        with torch.no_grad():
            scene, _, _ = model.complete_scan(raw, scan_points=scan, steps=8, guidance=3.5)
            if refine:
                scene = refiner.refine_cloud(scene)
        return torch.tensor(float(len(scene)))

    return [Case("complete vs complete + refine", f"{n:,}-pt scan → {10 * scan:,} → ×6 pts",
                 lambda: run(False), lambda: run(True), [], same_value=False)]


def determinism_cases(device: torch.device, quick: bool) -> list[Case]:
    """The cost of bitwise-repeatable runs (:mod:`distilkit.repro`): one training step of the quickstart's SCPNet
    student and of recipes/js3cnet_dskd.yaml's JS3C-Net student (batch 2, two scenes of their data), with PyTorch's
    deterministic algorithms off ('fast') and on ('naive'), alternately on the same trainer. MKL's strict mode
    (``MKL_CBWR``) is read when the process starts and is not toggled here."""
    import tempfile

    from distilkit.data.probe import _one_scene
    from distilkit.engine.probe import probe_trainer
    from distilkit.engine.resolve import resolve
    from distilkit.recipe import recipe_from_dict

    data = {"dataset": "synthetic-lidar", "params": {"scale": 8 if quick else 4, "input_frames": 4, "gt_frames": 10,
                                                     "azimuth_steps": 768}}
    models = {"SCPNet student": {"adapter": "scpnet", "params": {"frames": 1, "channels": 8, "point_mlp": [32, 64],
                                                                  "seg_channels": 16}},
              "JS3C-Net student": {"adapter": "js3cnet", "params": {"frames": 1}}}
    cases = []
    for label, model in models.items():
        recipe = {"name": "bench", "data": data, "stages": {"s": {"model": model, "train": {"batch_size": 2,
                                                                                              "device": device.type}}}}
        res = resolve(recipe_from_dict(recipe, "bench"), "bench")
        params = _one_scene(res.data_params).model_copy(update={"num_train": 2})
        trainer = probe_trainer(res, "s", params, Path(tempfile.mkdtemp(prefix="distilkit-bench-")), batch_size=2)
        batch = trainer.first_batch()
        trainer.student.train()

        def step(on: bool, trainer=trainer, batch=batch) -> Tensor:
            torch.use_deterministic_algorithms(on, warn_only=True)
            torch.utils.deterministic.fill_uninitialized_memory = False  # type: ignore[attr-defined]  # as repro does
            try:
                return torch.tensor(trainer.train_step(batch, 0)["loss"])
            finally:
                torch.use_deterministic_algorithms(False)

        size = f"train step, batch 2, {'x'.join(map(str, res.data_info.grid.shape))}"
        cases.append(Case(f"determinism: {label}", size, lambda step=step: step(False), lambda step=step: step(True),
                          [], same_value=False))
    return cases


def loader_cases(device: torch.device, quick: bool) -> list[Case]:
    """Training steps of the quickstart's teacher (a 4-frame SCPNet, batch 2, recipes/quickstart.yaml's data) through
    the stage's loader with 2 worker processes ('fast') and with none ('naive'): the batches are read and collated
    in the workers while the step runs. Each timing covers the loader's start and one epoch of steps (6; the quick
    mode: 2 steps on an 8-times smaller grid)."""
    import tempfile

    from distilkit.engine.loader import BatchPlan, train_batches
    from distilkit.engine.pipeline import Pipeline
    from distilkit.engine.trainer import Trainer
    from distilkit.recipe import recipe_from_dict

    data = {"scale": 8 if quick else 4, "num_train": 4 if quick else 12, "num_val": 1, "num_test": 1,
            "input_frames": 4, "gt_frames": 10, "azimuth_steps": 768}
    model = {"adapter": "scpnet", "params": {"frames": 4, "channels": 8, "point_mlp": [32, 64], "seg_channels": 16}}
    recipe = {"name": "bench", "data": {"dataset": "synthetic-lidar", "params": data},
              "stages": {"s": {"model": model, "train": {"batch_size": 2, "grad_clip": 10, "device": device.type}}}}
    pipe = Pipeline(recipe_from_dict(recipe, "bench"), Path(tempfile.mkdtemp(prefix="distilkit-bench-")), quiet=True)
    stage, train_set = pipe.resolved.stages["s"], pipe.dataset("train")
    plan = BatchPlan(len(train_set), 2, 0)
    torch.manual_seed(0)
    trainer = Trainer(stage, pipe.resolved.data_info, train_set, plan, device, collate=pipe.collate)
    steps = 2 if quick else plan.steps_per_epoch

    def run(workers: int) -> Tensor:
        losses = [trainer.train_step(batch.to(device), i)["loss"]
                  for i, batch in enumerate(train_batches(train_set, plan, pipe.collate, 0, steps, workers))]
        return torch.tensor(sum(losses) / len(losses))

    size = f"{steps} train steps, batch 2, {'x'.join(map(str, pipe.resolved.data_info.grid.shape))}"
    return [Case("loader: 2 workers vs none", size, lambda: run(2), lambda: run(0), [], same_value=False)]


def camera_cases(device: torch.device, quick: bool) -> list[Case]:
    """One training step of recipes/scribble2scene.yaml's camera student (VoxFormer-style, tiny, 2 images, frozen
    query proposals; batch 4 on its 64 x 64 x 8 grid, the quick mode 32 x 32 x 4) with RGO²D from the
    Teacher-Labeler and the image-feature MSE ('naive') and without distillation ('fast'): what distilling costs.
    Models have random weights (the step's cost does not depend on them)."""
    import tempfile

    from distilkit.data.probe import _one_scene
    from distilkit.engine.probe import probe_trainer
    from distilkit.engine.resolve import resolve
    from distilkit.recipe import recipe_from_dict

    data = {"dataset": "synthetic-lidar", "params": {"scale": 8 if quick else 4, "input_frames": 1, "gt_frames": 10,
                                                     "camera": {"previous": [3]}}}
    student = {"model": {"adapter": "voxformer", "params": {"frames": 2}}, "aux": {"proposal": {"from": "proposal"}},
               "task_losses": [{"name": "weighted_ce"}, {"name": "geo_scal"}],
               "train": {"batch_size": 4, "device": device.type}}
    features = {"student_features": "image_features", "teacher_features": "image_features"}
    stages = {"proposal": {"model": {"adapter": "voxformer-proposal"}, "train": {"metric": "iou"}},
              "teacher_labeler": {"model": {"adapter": "voxformer", "params": {"geometry": "ground-truth",
                                                                               "frames": 2}}},
              "plain": student,
              "rgo2d": {**student, "teacher": {"from": "teacher_labeler"},
                        "distill": [{"name": "rgo2d", "taps": features}]}}
    res = resolve(recipe_from_dict({"name": "bench", "data": data, "stages": stages}, "bench"), "bench")
    params = _one_scene(res.data_params).model_copy(update={"num_train": 4})
    steps = {}
    for name in ("plain", "rgo2d"):
        trainer = probe_trainer(res, name, params, Path(tempfile.mkdtemp(prefix="distilkit-bench-")), batch_size=4)
        batch = trainer.first_batch()
        trainer.student.train()
        steps[name] = lambda trainer=trainer, batch=batch: torch.tensor(trainer.train_step(batch, 0)["loss"])
    size = f"train step, batch 4, 2 images, {'x'.join(map(str, res.data_info.grid.shape))}"
    return [Case("camera student: no KD vs RGO²D", size, steps["plain"], steps["rgo2d"], [], same_value=False)]


def kitti_cases(device: torch.device, quick: bool) -> list[Case]:
    """The real-data path at SemanticKITTI's sizes, on a folder `distilkit data export-kitti` writes (one drive of
    HDL-64E-sized scans, ~120k points; --quick: 32 beams): reading and voxelising one scan with its labels
    ('fast') against reading a training sample that fuses 5 scans through the poses with its full-resolution voxel
    labels ('naive' column: the whole sample); and `distilkit eval` of one frame ('fast') against one frame
    predicted and written by `distilkit predict`'s writer ('naive'); a one-scan sample against the same with the
    camera's current and third-previous image decoded, resized and the scan projected as depth. Times per frame: a split of 4,071 frames (sequence
    08) takes 4,071 x the eval time, streaming one frame at a time."""
    from distilkit.data import semantickitti as skio
    from distilkit.data.datasets import SemanticKittiDataset
    from distilkit.data.export import export_kitti
    from distilkit.data.params import SemanticKittiParams, SyntheticParams
    from distilkit.data.info import ClassTable
    from distilkit.engine.predict import raw_ids
    from distilkit.metrics.official import evaluate_folder
    from distilkit.structures import VoxelGrid

    import tempfile

    import numpy as np

    root = Path(tempfile.mkdtemp(prefix="distilkit-bench-kitti-"))
    beams, steps = (32, 1024) if quick else (64, 2048)
    export_kitti(root, SyntheticParams(beams=beams, azimuth_steps=steps, gt_frames=4), ["08"], frames=6, stride=5)
    seq = root / "sequences" / "08"
    grid = VoxelGrid.semantickitti(1)
    n_points = len(skio.read_points(seq / "velodyne" / "000000.bin"))

    def read_voxelise() -> Tensor:
        pts = skio.read_points(seq / "velodyne" / "000000.bin")
        sem, inst = skio.read_point_labels(seq / "labels" / "000000.label", len(pts))
        idx, inside = grid.index(torch.from_numpy(pts[:, :3]))
        occupied = torch.zeros(grid.shape, dtype=torch.bool)
        occupied[tuple(idx[inside].T)] = True
        return occupied.sum().float() + float(sem.sum() % 7)

    dataset = SemanticKittiDataset(SemanticKittiParams(root=str(root), val=["08"], input_frames=5), "val")

    def fused() -> Tensor:
        s = dataset[0]
        return torch.tensor(float(len(s["points"]) + int(s["voxel_label"].sum())))

    preds = root / "preds"
    (preds / "sequences" / "08" / "predictions").mkdir(parents=True)
    raw = skio.read_voxel_labels(seq / "voxels" / "000000.label")
    raw.astype("<u2").reshape(-1).tofile(preds / "sequences" / "08" / "predictions" / "000000.label")
    for f in (seq / "voxels").glob("00000[1-9]*"):
        f.unlink()

    def evaluate() -> Tensor:
        return torch.tensor(evaluate_folder(root, preds, ["08"]).scores["miou"])

    labels = np.zeros(grid.shape, np.int64)

    def write() -> Tensor:
        raw_ids(ClassTable.semantickitti())[labels].astype("<u2").reshape(-1).tofile(preds / "write-test.label")
        return torch.tensor(0.0)

    from distilkit.data.kitti_camera import write_image

    (seq / "image_2").mkdir(exist_ok=True)
    noise = np.random.default_rng(0).integers(0, 256, (376, 1241, 3), dtype=np.uint8)  # incompressible: a worst case
    for j in range(6):
        write_image(seq / "image_2" / f"{j:06d}.png", noise)
    single = SemanticKittiDataset(SemanticKittiParams(root=str(root), val=["08"]), "val")
    camera = SemanticKittiDataset(SemanticKittiParams(root=str(root), val=["08"], camera={"previous": [3]}), "val")

    def lidar_sample() -> Tensor:
        return torch.tensor(float(len(single[0]["points"])))

    def camera_sample() -> Tensor:
        s = camera[0]
        return torch.tensor(float(s["image"].shape[0] + (s["depth"] > 0).sum()))

    return [Case("kitti: read+voxelise vs fused sample", f"{n_points:,}-pt scan; 5 scans, 256x256x32",
                 read_voxelise, fused, [], same_value=False),
            Case("kitti: LiDAR sample vs + camera", "1 scan vs + 2 images 1241x376 -> 1220x370, sparse depth",
                 lidar_sample, camera_sample, [], same_value=False),
            Case("kitti: eval vs predict-write, 1 frame", "256x256x32 uint16", evaluate, write, [], same_value=False)]


BENCHES: dict[str, Callable[[torch.device, bool], list[Case]]] = {
    "dskd": dskd_cases, "pkt": pkt_cases, "rgo2d": rgo2d_cases, "kd": kd_cases, "nst": nst_cases,
    "structural": structural_cases, "sampler": sampler_cases, "determinism": determinism_cases,
    "loader": loader_cases, "camera": camera_cases, "guidance": guidance_cases, "complete": complete_cases,
    "kitti": kitti_cases, "sparse": lambda device, quick: _sparse_cases(device, quick),
    "networks": lambda device, quick: _networks_cases(device, quick)}


def _sparse_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.sparse.bench import sparse_cases

    return sparse_cases(device, quick)


def _networks_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.netbench import networks_cases

    return networks_cases(device, quick)


def _fmt_mem(b: int | None) -> str:
    return "n/a" if b is None else f"{max(b, 0) / 2**20:,.0f} MiB"


def run_bench(names: list[str], device: str = "cpu", quick: bool = False, repeat: int | None = None) -> list[dict]:
    from rich.table import Table

    from distilkit.console import make_console

    from distilkit.errors import DistilkitError

    unknown = [n for n in names if n not in BENCHES]
    if unknown:
        import difflib

        hints = [difflib.get_close_matches(n, list(BENCHES), n=1) for n in unknown]
        raise DistilkitError(f"no benchmark for {', '.join(map(repr, unknown))}"
                             + "".join(f"; did you mean {h[0]!r}?" for h in hints if h)
                             + f" (available: {', '.join(BENCHES)})")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise DistilkitError("--device cuda: CUDA is not available on this machine")
    console = make_console()
    table = Table(title=f"distilkit bench — forward+backward, {dev.type}, torch {torch.__version__}, "
                        f"{torch.get_num_threads()} threads")
    for col in ("objective", "size", "fast ms", "fast peak", "naive ms", "naive peak", "speed-up",
                "rel. error (vs naive, or float64)"):
        table.add_column(col, justify="left" if col in ("objective", "size") else "right")
    rows = []
    notes: list[str] = []
    reps = repeat or (3 if not quick else 2)
    for name in names or list(BENCHES):
        for case in BENCHES[name](dev, quick):
            with console.status(f"{case.objective} {case.size}"):
                ms, peak, val = case.measure() if case.measure else time_fb(case.fast, case.inputs, dev, reps)
                row = {"objective": case.objective, "size": case.size, "fast_ms": ms, "fast_peak": peak, "value": val}
                if case.reference is not None:
                    with torch.no_grad():
                        ref = float(case.reference())
                    row.update(rel_err=abs(val - ref) / max(abs(ref), 1e-30))
                if case.naive is not None:
                    nms, npeak, nval = time_fb(case.naive, case.inputs, dev, reps)
                    row.update(naive_ms=nms, naive_peak=npeak, speedup=nms / ms)
                    if case.same_value:
                        row.update(rel_err=abs(val - nval) / max(abs(nval), 1e-30))
            rows.append(row)
            if case.note is not None:
                notes.append(case.note(row))
            table.add_row(case.objective, case.size, f"{ms:,.1f}", _fmt_mem(peak),
                          f"{row['naive_ms']:,.1f}" if "naive_ms" in row else "—",
                          _fmt_mem(row.get("naive_peak")) if "naive_ms" in row else "—",
                          (f"{row['speedup']:,.0f}×" if row["speedup"] >= 10 else f"{row['speedup']:.2f}×") if "speedup" in row else "—",
                          f"{row['rel_err']:.1e}" if "rel_err" in row else "—")
    console.print(table)
    for line in notes:
        console.print(line, highlight=False, soft_wrap=True)
    return rows
