from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

import pytest

if os.environ.get("PYTEST_XDIST_WORKER"):  # pytest -n N: one thread per worker (before torch loads), so the
    os.environ["OMP_NUM_THREADS"] = "1"  # workers share the cores instead of fighting over them
    os.environ["MKL_NUM_THREADS"] = "1"
    # xdist's workers inherit COLUMNS=80 / LINES=24 from execnet; distilkit honours COLUMNS (a user's width), so the
    # workers print as a plain pipe does, like the tests run with -n 0
    os.environ.pop("COLUMNS", None)
    os.environ.pop("LINES", None)

import distilkit  # noqa: F401  first: it sets MKL's reproducibility before any test multiplies a matrix
from distilkit.repro import warm_vector_math

warm_vector_math()  # MKL's vector maths settled in one thread before a test computes anything twice (repro)

ROOT = Path(__file__).resolve().parents[1]


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--device", default="cpu", choices=("cpu", "cuda"),
                     help="the device the tests build their tensors and models on (default cpu; cuda: the GPU check)")


def pytest_configure(config: pytest.Config) -> None:
    if config.pluginmanager.hasplugin("xdist"):
        config.pluginmanager.register(_XdistGroupIds(), "distilkit-xdist-group-ids")
    if config.getoption("--device") == "cuda":
        import torch

        if not torch.cuda.is_available():
            built = f"built with CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
            pytest.exit(f"--device cuda: CUDA is not available on this machine (torch {torch.__version__}, {built})",
                        returncode=4)


@pytest.fixture
def device(request: pytest.FixtureRequest) -> "torch.device":
    """The device of ``--device`` (cpu by default): a test that takes it runs its assertions there."""
    import torch

    return torch.device(request.config.getoption("--device"))


# markers by file, for a quick run of what a change touches: `python -m pytest -m "not slow and not network and not
# processes"` (README); the README's command runs them all. network: the papers' networks whole (their parity with
# the releases, float64 and bf16); processes: tests whose point is a process of its own (killed, signalled, two at
# once, torchrun, Slurm, a sweep's jobs, a fresh interpreter's imports)
BY_FILE = {
    "network": {"test_scpnet_paper.py", "test_scpnet_release.py", "test_js3cnet_paper.py",
                "test_js3cnet_release.py", "test_lidiff_paper.py", "test_lidiff_release.py",
                "test_voxformer_paper.py", "test_voxformer_release.py", "test_dean_paper.py", "test_amp.py",
                "test_bench_step.py"},
    "processes": {"test_faults.py", "test_distributed.py", "test_slurm_plan.py", "test_slurm_real.py",
                  "test_new_user_faults.py", "test_ema_teacher.py", "test_sweep.py", "test_reproducible.py",
                  "test_gpu_check.py", "test_trackers.py", "test_catalogue.py", "test_threads.py", "test_cards.py",
                  "test_adapter_cards.py"},
}


@pytest.hookimpl(tryfirst=True)  # before pytest's own -m selection reads the markers
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark each test of a file in ``BY_FILE`` with its marker, and ``device`` every test that takes the ``device``
    fixture, so that the GPU check runs just those (``pytest -m "device and not slow" --device cuda``) — but not a
    test marked ``gpus(n)`` under ``--device cuda`` on a machine with fewer GPUs: it computes on the CPU there (the
    two-process tests on one GPU)."""
    cuda = config.getoption("--device") == "cuda"
    gpus = None
    for item in items:
        for name, files in BY_FILE.items():
            if item.path.name in files:
                item.add_marker(getattr(pytest.mark, name))
        if "device" not in getattr(item, "fixturenames", ()):
            continue
        needs = item.get_closest_marker("gpus")
        if cuda and needs is not None:
            if gpus is None:
                import torch

                gpus = torch.cuda.device_count()
            if gpus < needs.args[0]:
                continue
        item.add_marker(pytest.mark.device)


def on(device, gpus: int = 1) -> str:
    """The device a test's recipe trains on: ``device`` (the fixture's) where the machine has ``gpus`` GPUs for
    it, else the CPU (a run of two processes takes a GPU each: on one GPU they train on the CPU)."""
    import torch

    device = str(device)
    return device if device == "cpu" or torch.cuda.device_count() >= gpus else "cpu"


def can_fork() -> bool:
    """Whether a child forked from this process can train. Not on a machine with a GPU: there PyTorch's autograd
    starts its device threads at the first backward (whichever device it ran on) and then refuses to run in a forked
    child ("Unable to handle autograd's threading in combination with fork-based multiprocessing"), and a child of a
    process that used CUDA gets "CUDA error: initialization error" (Adam asks CUDA whether it is capturing a graph).
    Both seen on an H200 (torch 2.11); the tests that fork to skip re-importing torch spawn there instead."""
    import torch

    return not torch.cuda.is_available()


def process_context():
    """The multiprocessing context of a test's child process: fork where :func:`can_fork`, else spawn (the target
    must be a module-level function of an importable module; it imports torch and distilkit again, ~4 s)."""
    import multiprocessing

    return multiprocessing.get_context("fork" if can_fork() else "spawn")


FIXTURES = Path(__file__).resolve().parent / "fixtures"  # copied in; tests never read outside the repo

EXPORT_SET = ["beams=16", "azimuth_steps=256", "gt_frames=5", "seed=3"]  # a small exported SemanticKITTI folder


def export_kitti(root: Path, *extra: str) -> Path:
    """A SemanticKITTI folder of two 11-scan sequences exported from the synthetic streets into ``root``
    (``extra``: more export-kitti arguments, e.g. ``--camera``, then ``--set`` values)."""
    from distilkit.cli import main

    flags = [a for a in extra if a.startswith("--")]
    values = [a for a in extra if not a.startswith("--")]
    assert main(["data", "export-kitti", str(root), "--frames", "11", *flags, "--set", *EXPORT_SET, *values]) == 0
    return root


TINY_DATA = {"scale": 8, "num_train": 2, "num_val": 1, "num_test": 1, "input_frames": 2, "gt_frames": 3, "beams": 16,
             "azimuth_steps": 256}


@pytest.fixture(autouse=True, scope="session")
def _cache(tmp_path_factory: pytest.TempPathFactory) -> None:
    os.environ.setdefault("DISTILKIT_CACHE", str(tmp_path_factory.mktemp("cache")))


_RENDERS = [False]  # whether the test being set up looks at the pictures (marked plots)

# the tests' child processes (`distilkit run` of a sweep's jobs, torchrun, a requeued job...) find
# tests/_child_site/sitecustomize.py, which gives them the stand-in below (tests/_child_site/_closed_plots.py) where
# DISTILKIT_TEST_CLOSED_PLOTS is set
CHILD_SITE = str(Path(__file__).resolve().parent / "_child_site")
if CHILD_SITE not in os.environ.get("PYTHONPATH", "").split(os.pathsep):
    os.environ["PYTHONPATH"] = os.pathsep.join([CHILD_SITE, *filter(None, os.environ.get("PYTHONPATH", "").split(
        os.pathsep))])


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """Before any fixture of ``item`` is set up: module and session fixtures built for it, and the child processes
    it starts, render as it would."""
    _RENDERS[0] = item.get_closest_marker("plots") is not None
    if _RENDERS[0]:
        os.environ.pop("DISTILKIT_TEST_CLOSED_PLOTS", None)
    else:
        os.environ["DISTILKIT_TEST_CLOSED_PLOTS"] = "1"


@pytest.fixture(autouse=True, scope="session")
def _render_plots_only_where_looked_at() -> "Iterator[None]":
    """Rendering PNGs is two thirds of a tiny run's time (matplotlib's text layout): a test that does not look at
    the pictures — every shared fixture built for one, and the child processes it starts (tests/_child_site) — gets
    each figure closed and an empty file where the PNG goes (every report path still runs, up to the drawing); tests
    marked ``plots`` render them for real."""
    from distilkit.report import plots

    from _child_site._closed_plots import closing

    real = plots.save
    plots.save = closing(real, lambda: _RENDERS[0])
    yield
    plots.save = real


class _XdistGroupIds:
    """``--dist loadgroup`` keeps the tests of one ``xdist_group`` on one worker by an ``@group`` suffix of their
    ids; pytest-xdist 3.8 writes it to ``item._nodeid``, which pytest 9.2 no longer reads (its id is ``_id``), so the
    groups are ignored without a word (pytest-dev/pytest-xdist#1386). Put the suffix where pytest reads it, where
    xdist's own did not land."""

    @pytest.hookimpl(trylast=True)
    def pytest_collection_modifyitems(self, config: pytest.Config, items: list[pytest.Item]) -> None:
        if not getattr(config.option, "loadgroup", False):  # set in xdist's workers under --dist loadgroup
            return
        for item in items:
            names = sorted({str(m.args[0] if m.args else m.kwargs.get("name", "default"))
                            for m in item.iter_markers("xdist_group")})
            if names and not item.nodeid.endswith("@" + "_".join(names)):
                from _pytest.nodeid import coerce_node_id

                item._id = coerce_node_id(f"{item.nodeid}@{'_'.join(names)}")


def tiny_recipe(name: str = "tiny", steps: int = 2, distill: bool = True, adapter: str = "scpnet",
                device="cpu") -> dict:
    """A teacher and (``distill``) a DSKD student on the tiny synthetic scenes, both training on ``device``
    (``train.device``, never ``auto``: a test about what is computed passes the ``device`` fixture; the default keeps
    a test of files, text or options on the CPU whatever ``--device`` says)."""
    params = {"channels": 4, "point_mlp": [8], "seg_channels": 4} if adapter == "scpnet" else \
        {"seg_channels": 4, "embed": 4, "ssc_channels": 4, "pvi_hidden": 4, "knn": 4}
    train = {"steps": steps, "batch_size": 1, "eval_every": steps, "log_every": 1, "checkpoint_every": 1,
             "device": str(device)}
    stages = {
        "teacher": {"model": {"adapter": adapter, "params": {**params, "frames": 2}}, "train": train},
    }
    if distill:
        stages["student"] = {"model": {"adapter": adapter, "params": {**params, "frames": 1}},
                             "teacher": {"from": "teacher"},
                             "distill": [{"name": "dskd", "weight": 10.0}], "train": train}
    return {"schema_version": 1, "name": name, "seed": 0,
            "data": {"dataset": "synthetic-lidar", "params": dict(TINY_DATA)}, "stages": stages}


def folder_recipe(root, name: str = "kitti", dataset: str = "semantickitti", frames: int = 1, steps: int = 1,
                  batch_size: int = 1, eval_every: int | None = None, stage: str = "scpnet", publish=(),
                  device="cpu", **data) -> dict:
    """A one-stage recipe: a tiny SCPNet on a SemanticKITTI-format folder at ``root`` (``data``: the dataset's
    other parameters, e.g. ``train=["00"], val=["08"], scale=4``) training on ``device`` (as :func:`tiny_recipe`)."""
    params = {"channels": 4, "point_mlp": [8], "seg_channels": 4, "frames": frames}
    spec = {"model": {"adapter": "scpnet", "params": params}, **({"publish": list(publish)} if publish else {}),
            "train": {"steps": steps, "batch_size": batch_size, "eval_every": eval_every or steps,
                      "device": str(device)}}
    return {"schema_version": 1, "name": name, "seed": 0,
            "data": {"dataset": dataset, "params": {"root": str(root), **data}}, "stages": {stage: spec}}


def make_trainer(pipe, stage_name: str, teacher=None, world=None, device=None):
    """The :class:`~distilkit.engine.train.trainer.Trainer` of a pipeline's stage at its seed, on ``device`` (the
    CPU unless given: a test of what the trainer is built from; one of what it computes passes the ``device``
    fixture), without a run."""
    import torch

    from distilkit.engine.train.distributed import SINGLE
    from distilkit.engine.train.loader import BatchPlan
    from distilkit.engine.train.trainer import Trainer

    world = world or SINGLE
    stage = pipe.resolved.stages[stage_name]
    train_set = pipe.dataset("train")
    plan = BatchPlan(len(train_set), stage.spec.train.batch_size, 0, world)
    return Trainer(stage, pipe.resolved.data_info, train_set, plan, torch.device(device or "cpu"),
                   collate=pipe.collate, teacher=teacher, world=world)


def on_device_matches(fast, naive, inputs, device, rel: float = 1e-6) -> None:
    """``fast`` of ``inputs`` copied to ``device`` against ``naive`` of them on the CPU: value and the gradients of
    the inputs that require one."""
    import torch

    here = [x.detach().to(device).requires_grad_(x.requires_grad) if x is not None else None for x in inputs]
    a, b = fast(*here), naive(*inputs)
    a_value, b_value = a.detach().cpu(), b.detach()
    assert bool((a_value - b_value).abs() <= rel * b_value.abs() + 1e-12), (float(a_value), float(b_value))
    wants = [i for i, x in enumerate(inputs) if x is not None and x.requires_grad]
    ga = torch.autograd.grad(a, [here[i] for i in wants], allow_unused=True)
    gb = torch.autograd.grad(b, [inputs[i] for i in wants], allow_unused=True)
    for x, y in zip(ga, gb):
        x = torch.zeros(()) if x is None else x.cpu()
        y = torch.zeros(()) if y is None else y
        assert (x - y).norm() <= rel * y.norm() + 1e-12


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item: pytest.Item) -> None:
    """After a slow test: glibc's heap keeps what a large step freed (a worker that ran a paper network at its full
    grid held several GiB it no longer used), and the two workers share the machine's memory; ``malloc_trim`` gives
    the free pages back to the system. Milliseconds; only where glibc is the allocator."""
    if item.get_closest_marker("slow") is None:
        return
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        trim = ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to give back this way
        trim = None
    if trim is not None:
        trim(0)
