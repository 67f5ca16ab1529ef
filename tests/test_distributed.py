"""Multi-process training: two processes take the same step as one process on the same global batch — student,
FitNets' connector and every other trainable — on the device of ``--device`` (gloo on the CPU; on CUDA, NCCL where
each process has a GPU of its own, gloo through the host on one GPU), and `distilkit run --nproc-per-node 2`
(torchrun) trains a recipe to the end with one writer."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any, Iterator

import pytest
import torch
import torch.multiprocessing as mp
import yaml

from conftest import can_fork, make_trainer, on, process_context, tiny_recipe
from distilkit.engine.train.distributed import World, leave
from distilkit.engine.assemble.runs import build_model, freeze
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import DistilkitError
from distilkit.recipe import recipe_from_dict


@contextlib.contextmanager
def camera_registered() -> Iterator[None]:
    """The camera-style toy of test_contracts (no BatchNorm; its CE is a mean over equally many voxels per sample)
    registered while the context is open, then removed again where this added it: other tests iterate over the
    registries (``distilkit schema --markdown`` against docs/reference/recipe.md)."""
    import test_contracts as tc
    from distilkit.registry import ADAPTERS, DATASETS

    added = [r for r, name in ((DATASETS, "tiny-camera-data"), (ADAPTERS, "tiny-camera")) if name not in r]
    if "tiny-camera-data" not in DATASETS:
        DATASETS.add("tiny-camera-data", tc.camera_split, description="test", paper="tests",
                     params=tc.CameraDataParams, info=tc.camera_info, collate=tc.collate_camera, version=1,
                     has_split=lambda p, s: True)
    if "tiny-camera" not in ADAPTERS:
        ADAPTERS.add("tiny-camera", tc.TinyCamera, description="test", paper="tests",
                     consumes=tuple(tc.TinyCamera.TAPS.values()))
    try:
        yield
    finally:
        for registry in added:
            registry.remove("tiny-camera-data" if registry is DATASETS else "tiny-camera")


def one_step(world: World, folder: Path, device: str = "cpu") -> dict[str, dict[str, torch.Tensor]]:
    """One training step of a distilled student (CE + KD + FitNets with its linear connector) on global batch 0;
    the gradients it took and the weights after it, by qualified name. On CUDA without TF32: cuDNN's convolutions
    use it by default (torch.backends.cudnn.allow_tf32), and its 10-bit products over a batch of 4 and of 2 round
    differently; what is compared here is the processes' reduction, not TF32."""
    flags = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        with camera_registered():
            return _one_step(world, folder, device)
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = flags


def _one_step(world: World, folder: Path, device: str) -> dict[str, dict[str, torch.Tensor]]:
    train = {"steps": 2, "batch_size": 4, "eval_every": 2}
    recipe = {"schema_version": 1, "name": "ddp", "seed": 0, "data": {"dataset": "tiny-camera-data", "params": {}},
              "stages": {"teacher": {"model": {"adapter": "tiny-camera", "params": {"channels": 6}}, "train": train},
                         "student": {"model": {"adapter": "tiny-camera", "params": {}}, "teacher": {"from": "teacher"},
                                     "task_losses": [{"name": "ce"}],
                                     "distill": [{"name": "kd", "weight": 1.0},
                                                 {"name": "fitnets", "weight": 1.0,
                                                  "taps": {"student": "image_features", "teacher": "image_features"}}],
                                     "train": train}}}
    pipe = Pipeline(recipe_from_dict(recipe), folder, quiet=True)
    stage, info = pipe.resolved.stages["student"], pipe.resolved.data_info
    torch.manual_seed(7)
    teacher = freeze(build_model(stage.teacher, info, "teacher").to(device))
    trainer = make_trainer(pipe, "student", teacher, world, device)
    batch = trainer.first_batch().to(device)
    assert batch.size == 4 // world.size  # this process's share of the global batch
    trainer.train_step(batch, 0)
    named = trainer.named_trainables()
    assert any(n.startswith("connector.") for n, _ in named)  # FitNets' regressor trains too
    assert all(p.grad.device.type == torch.device(device).type for _, p in named)
    return {"grads": {n: p.grad.detach().cpu().clone() for n, p in named},
            "weights": {n: p.detach().cpu().clone() for n, p in named}}


def backend(device: str) -> str:
    """The process group of a run on ``device``: gloo on the CPU; on CUDA, NCCL for CUDA tensors where each process
    has a GPU of its own (NCCL refuses two ranks on one GPU), else gloo for them too (it copies through the host)."""
    if device != "cuda":
        return "gloo"
    return "cpu:gloo,cuda:nccl" if torch.cuda.device_count() >= 2 else "cpu:gloo,cuda:gloo"


def _worker(rank: int, size: int, init_file: str, folder: str, device: str = "cpu") -> None:
    """One of two processes: a training step (:func:`one_step`) on ``device``, then the evaluation of
    :func:`scored` (on the CPU, gloo), each saved for the parent."""
    torch.set_num_threads(1)
    if device == "cuda":
        torch.cuda.set_device(rank % torch.cuda.device_count())
    torch.distributed.init_process_group(backend(device), init_method=f"file://{init_file}", rank=rank,
                                         world_size=size)
    world = World(rank, size)
    torch.save(one_step(world, Path(folder), device), Path(folder) / f"out{rank}.pt")
    torch.save(scored(world, Path(folder) / f"rank{rank}"), Path(folder) / f"eval{rank}.pt")
    leave(world)  # as `distilkit run` ends a process: gloo's teardown can abort at exit


@pytest.fixture(scope="module")
def two_processes(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """One process's training step and evaluation, and two more processes' (one process group for both), on the
    device of ``--device``; read by the two tests below. The two are forked from this one (what they compute is in
    a process of their own; they skip importing torch and distilkit again, ~4 s of CPU each), spawned on a machine
    with a GPU, where a forked child cannot train (conftest.can_fork)."""
    device = request.config.getoption("--device")
    tmp = tmp_path_factory.mktemp("two_processes")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as each worker; given back after, since later tests compare with subprocesses
    try:
        single = one_step(World(), tmp / "single", device)
    finally:
        torch.set_num_threads(threads)
    single_eval = scored(World(), tmp / "single_eval")
    mp.start_processes(_worker, args=(2, str(tmp / "init"), str(tmp), device), nprocs=2, join=True,
                       start_method="fork" if can_fork() else "spawn")
    return {"single": single, "outs": [torch.load(tmp / f"out{r}.pt", weights_only=True) for r in range(2)],
            "single_eval": single_eval, "evals": [torch.load(tmp / f"eval{r}.pt", weights_only=True) for r in range(2)]}


@pytest.mark.xdist_group("two_processes")
def test_two_processes_take_the_same_step_as_one_on_the_global_batch(two_processes: dict[str, Any], device) -> None:
    """Each of the two processes' gradients and weights after the step equal the one process's on the global batch
    (and the step took a gradient)."""
    single, outs = two_processes["single"], two_processes["outs"]
    for name, grad in single["grads"].items():
        for out in outs:
            torch.testing.assert_close(out["grads"][name], grad, rtol=1e-5, atol=1e-7,
                                       msg=lambda m, n=name: f"gradient of {n}: {m}")
            torch.testing.assert_close(out["weights"][name], single["weights"][name], rtol=1e-5, atol=1e-7,
                                       msg=lambda m, n=name: f"{n} after the step: {m}")
    assert any(g.abs().sum() > 0 for g in single["grads"].values())


def test_a_global_batch_that_does_not_split_is_refused(tmp_path: Path) -> None:
    with pytest.raises(DistilkitError, match=r"train.batch_size 4 is the global batch of 3 processes; it must be a "
                                             r"multiple of 3"):
        one_step(World(0, 3), tmp_path)  # refused before any collective operation


def clean_env() -> dict[str, str]:
    """This process's environment without Slurm's or torchrun's variables, one thread per process."""
    base = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "RANK", "WORLD_SIZE", "LOCAL_RANK",
                                                                      "MASTER_"))}
    return {**base, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def torchrun_run(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One `distilkit run --nproc-per-node 2` (torchrun) of the tiny teacher and DSKD student, 3 steps of global batch
    2 each, into ``runs/`` beside its recipe ``r.yaml`` (the folder returned): read by the two tests below. On the
    device of ``--device`` where each process has a GPU of its own: under ``--device cuda`` on a machine with fewer
    than two GPUs the recipe says ``device: cpu`` (two processes on one GPU are refused; on the CPU they reduce with
    gloo over the host whatever GPUs the machine has), and the tests are not marked ``device`` there."""
    recipe: dict[str, Any] = tiny_recipe(steps=3, device=on(request.config.getoption("--device"), gpus=2))
    for stage in recipe["stages"].values():
        stage["train"].update(batch_size=2, eval_every=3)
    from distilkit.cli import main

    folder = tmp_path_factory.mktemp("torchrun")
    (folder / "r.yaml").write_text(yaml.safe_dump(recipe))
    with pytest.MonkeyPatch.context() as patch:  # the command in this process: it starts torchrun, which starts two
        env = clean_env()
        for key in [k for k in os.environ if k not in env]:
            patch.delenv(key)
        for key in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            patch.setenv(key, env[key])
        assert main(["run", str(folder / "r.yaml"), "-o", str(folder / "runs"), "-q", "--nproc-per-node", "2"]) == 0
    return folder


@pytest.mark.gpus(2)
@pytest.mark.xdist_group("torchrun")
def test_distilkit_run_with_two_processes_trains_with_one_writer(torchrun_run: Path, device) -> None:
    """Both stages of the torchrun run finished with 2 processes, and each step's loss was logged once."""
    for name in ("teacher", "student"):
        (run,) = (torchrun_run / "runs" / "tiny").glob(f"{name}-*")
        summary = json.loads((run / "summary.json").read_text())
        assert summary["processes"] == 2 and summary["status"] == "finished"
        steps = [json.loads(x).get("step") for x in (run / "metrics.jsonl").read_text().splitlines()
                 if "loss" in json.loads(x)]
        assert steps == [1, 2, 3]  # each step logged once: one writer


@pytest.mark.gpus(2)
@pytest.mark.xdist_group("torchrun")
def test_two_slurm_tasks_train_as_torchrun_would_start_them(torchrun_run: Path, tmp_path: Path, device) -> None:
    """`srun -n 2 distilkit run ... --stage teacher`: two processes with Slurm's task variables (as srun sets them in
    a step) and no torchrun train one run together, and its weights equal those of the torchrun run's teacher (the
    same recipe, device and global batch) bit for bit. On the CPU the two are forked from this process (what they
    are is their Slurm variables, not a fresh import of torch: ~4 s of CPU each; spawned on a machine with a GPU,
    conftest.can_fork); a recipe on CUDA starts them as `distilkit run` processes."""
    path = torchrun_run / "r.yaml"
    argv = ["run", str(path), "-o", str(tmp_path / "slurm"), "-q", "--stage", "teacher"]
    envs = [{**clean_env(), "SLURM_STEP_ID": "0", "SLURM_NTASKS": "2", "SLURM_PROCID": str(i), "SLURM_LOCALID": str(i),
             "SLURM_JOB_ID": str(4000 + os.getpid() % 1000), "SLURM_STEP_NODELIST": "localhost"} for i in range(2)]
    if yaml.safe_load(path.read_text())["stages"]["teacher"]["train"]["device"] == "cpu":
        logs = [tmp_path / f"task{i}.log" for i in range(2)]
        procs = [process_context().Process(target=_slurm_task, args=(argv, env, log))
                 for env, log in zip(envs, logs)]
        for proc in procs:
            proc.start()
        for proc in procs:
            proc.join(timeout=600)
        assert all(p.exitcode == 0 for p in procs), [log.read_text()[-2000:] for log in logs if log.is_file()]
    else:
        popens = [subprocess.Popen([sys.executable, "-m", "distilkit", *argv], env=env, stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE, text=True) for env in envs]
        outs = [p.communicate(timeout=600) for p in popens]
        assert all(p.returncode == 0 for p in popens), [o[1][-2000:] for o in outs]
    (a,) = (tmp_path / "slurm" / "tiny").glob("teacher-*")
    (b,) = (torchrun_run / "runs" / "tiny").glob("teacher-*")
    assert json.loads((a / "summary.json").read_text())["processes"] == 2
    x = torch.load(a / "checkpoints" / "last.pt", weights_only=True)["student"]
    y = torch.load(b / "checkpoints" / "last.pt", weights_only=True)["student"]
    assert all(torch.equal(x[k], y[k]) for k in y)


def _slurm_task(argv: list[str], env: dict[str, str], log: Path) -> None:
    """One Slurm task in a child process: ``distilkit ARGV`` with the task's environment alone and its one thread
    (OMP_NUM_THREADS=1, as in the environment), its output to ``log``."""
    os.environ.clear()
    os.environ.update(env)
    torch.set_num_threads(1)
    fd = os.open(log, os.O_WRONLY | os.O_CREAT)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    from distilkit.cli import main

    sys.exit(main(argv))


def test_the_first_host_of_a_slurm_node_list(monkeypatch, tmp_path) -> None:
    """Read off the list where scontrol is missing (and, where Slurm is installed, as scontrol expands it)."""
    from distilkit.engine.train.distributed import first_host

    lists = {"node[03-05,07],gpu1": "node03", "gpu1,node[1-2]": "gpu1", "localhost": "localhost",
             "n[7,9]": "n7"}
    import shutil

    if shutil.which("scontrol"):
        assert {k: first_host(k) for k in lists} == lists
    monkeypatch.setenv("PATH", str(tmp_path))  # no scontrol
    assert {k: first_host(k) for k in lists} == lists


def scored(world: World, folder: Path) -> dict[str, Any]:
    """An SCPNet's SSC confusion over 5 validation scenes, this process's share merged with the others', and the
    number of scenes each process scored."""
    from distilkit.engine.train.evaluate import _merged
    from distilkit.engine.train.loader import eval_batches
    from distilkit.metrics.registered import SSCScore

    recipe = tiny_recipe(steps=1, distill=False)
    recipe["data"]["params"]["num_val"] = 5
    pipe = Pipeline(recipe_from_dict(recipe), folder, quiet=True)
    torch.manual_seed(3)
    model = build_model(pipe.resolved.stages["teacher"].student, pipe.resolved.data_info).eval()
    metric, mine = SSCScore(model.info), 0
    with torch.no_grad():
        for batch in eval_batches(pipe.dataset("val"), 2, pipe.collate, world):
            metric.update(model(batch)[model.PREDICTION_TAP], batch)
            mine += batch.size
    (merged,), _, total = _merged([metric], 0.0, mine, world)
    return {"confusion": merged.acc.confusion, "mine": mine, "total": total}


@pytest.mark.xdist_group("two_processes")
def test_two_processes_evaluate_each_scene_once_and_their_merged_confusion_is_one_processs(
        two_processes: dict[str, Any]) -> None:
    """Of 5 validation scenes the two processes score 2 and 3, each knows the total, and the merged confusion of
    each equals one process's (which is not empty)."""
    single, outs = two_processes["single_eval"], two_processes["evals"]
    assert [o["mine"] for o in outs] == [2, 3] and all(o["total"] == 5 for o in outs)  # each scene once
    assert single["confusion"].sum() > 0
    for out in outs:
        assert torch.equal(out["confusion"], single["confusion"])


def _two_processes_here(monkeypatch, gpus: int, local_rank: int = 1) -> list[tuple[str, Any]]:
    """This process as one of two that torchrun started on a node with ``gpus`` GPUs (CUDA faked on the CPU); the
    calls world_from_env makes to set a GPU and start the process group, recorded instead of made."""
    calls: list[tuple[str, Any]] = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: gpus > 0)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: gpus)
    monkeypatch.setattr(torch.cuda, "set_device", lambda d: calls.append(("set_device", d)))
    monkeypatch.setattr(torch.distributed, "is_initialized", lambda: False)
    monkeypatch.setattr(torch.distributed, "init_process_group", lambda backend, **kw: calls.append(("group", backend)))
    for key in [k for k in os.environ if k.startswith("SLURM_")] + ["MASTER_ADDR", "MASTER_PORT"]:
        monkeypatch.setenv(key, "")
        monkeypatch.delenv(key)  # as before the test afterwards, also what from_slurm writes
    for key, value in {"WORLD_SIZE": "2", "RANK": str(local_rank), "LOCAL_RANK": str(local_rank),
                       "LOCAL_WORLD_SIZE": "2"}.items():
        monkeypatch.setenv(key, value)
    return calls


def test_more_processes_than_gpus_for_a_cuda_stage_is_refused_naming_both(monkeypatch) -> None:
    """Two processes on a one-GPU node and a stage on CUDA: both processes (rank 0 too, which has a GPU: it would
    otherwise wait for the other in the process group) stop before the group starts, naming the processes and the
    GPU count; nothing is put on a GPU that does not exist (``set_device(1)``: invalid device ordinal)."""
    from distilkit.engine.train.distributed import world_from_env

    for rank in (1, 0):
        calls = _two_processes_here(monkeypatch, gpus=1, local_rank=rank)
        with pytest.raises(DistilkitError) as err:
            world_from_env({"teacher": torch.device("cuda"), "student": torch.device("cpu")})
        assert str(err.value) == (
            f"2 processes on this node (torchrun's --nproc-per-node 2; this one LOCAL_RANK {rank}) and stage teacher "
            "trains on cuda, one GPU per process: this node has 1 GPU (torch.cuda.device_count()); start at most 1 "
            "per node, or train on the CPU with --set 'stages.*.train.device=cpu' (gloo over the host)")
        assert calls == []
    # Slurm's tasks (no torchrun): the same, from its tasks per node
    calls = _two_processes_here(monkeypatch, gpus=1)
    for key in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "LOCAL_WORLD_SIZE"):
        monkeypatch.delenv(key)
    for key, value in {"SLURM_STEP_ID": "0", "SLURM_NTASKS": "2", "SLURM_PROCID": "0", "SLURM_LOCALID": "0",
                       "SLURM_STEP_TASKS_PER_NODE": "2", "SLURM_STEP_NODELIST": "localhost"}.items():
        monkeypatch.setenv(key, value)
    monkeypatch.setenv("PATH", "")  # no scontrol
    with pytest.raises(DistilkitError, match=r"^2 processes on this node \(Slurm's SLURM_STEP_TASKS_PER_NODE=2; "
                                             r"this one SLURM_LOCALID 0\) and stage teacher trains on cuda, one GPU "
                                             r"per process: this node has 1 GPU"):
        world_from_env({"teacher": torch.device("cuda")})
    assert calls == []


def test_processes_whose_stages_train_on_the_cpu_use_gloo_and_no_gpu_whatever_the_machine_has(monkeypatch) -> None:
    from distilkit.engine.train.distributed import world_from_env

    calls = _two_processes_here(monkeypatch, gpus=1)
    world = world_from_env({"teacher": torch.device("cpu"), "student": torch.device("cpu")})
    assert (world.rank, world.size, world.local_rank) == (1, 2, 1)
    assert calls == [("group", "gloo")]  # no set_device, no NCCL
    calls = _two_processes_here(monkeypatch, gpus=2)  # a GPU each: the stage on CUDA gets this process's
    world_from_env({"teacher": torch.device("cuda")})
    assert calls == [("set_device", 1), ("group", "cpu:gloo,cuda:nccl")]
    calls = _two_processes_here(monkeypatch, gpus=1)  # stages not given: as `auto` would pick (a GPU: CUDA)
    with pytest.raises(DistilkitError, match=r"and the stages \(train.device auto, a GPU available\) train on cuda"):
        world_from_env()


@pytest.mark.parametrize("where", ["cuda", "auto", "cpu"])
def test_distilkit_run_refuses_more_processes_than_gpus_before_starting_torchrun(tmp_path: Path, monkeypatch,
                                                                                 capsys, where) -> None:
    """`distilkit run --nproc-per-node 2` on a one-GPU machine: with a stage on CUDA (or on `auto`, which picks the
    GPU) one line and status 2, torchrun not started; with the stages on the CPU (here by --set) torchrun starts."""
    import distilkit.engine.train.launch as launch
    from distilkit.cli import main

    _two_processes_here(monkeypatch, gpus=1)
    for key in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "LOCAL_WORLD_SIZE"):  # the launcher, not one of its processes
        monkeypatch.delenv(key)
    started: list[int] = []
    monkeypatch.setattr(launch, "launch", lambda args, nproc, *rest: started.append(nproc) or 0)
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(tiny_recipe(steps=1, distill=False, device="cuda")))
    code = main(["run", str(path), "-o", str(tmp_path / "runs"), "--nproc-per-node", "2",
                 *([] if where == "cuda" else ["--set", f"stages.*.train.device={where}"])])
    err = capsys.readouterr().err
    if where == "cpu":
        assert code == 0 and started == [2] and err == ""
        return
    assert code == 2 and started == [] and err == (
        "error: 2 processes on this node (--nproc-per-node 2) and stage teacher trains on cuda, one GPU per process: "
        "this node has 1 GPU (torch.cuda.device_count()); start at most 1 per node, or train on the CPU with "
        "--set 'stages.*.train.device=cpu' (gloo over the host)\n")
