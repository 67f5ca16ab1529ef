"""A frozen teacher's outputs on disk: what a store holds and how it is read back (issue 58).

A store is a folder ``<output>/<recipe>/teacher-store-<key>/``: shards ``shard-NNNNN.safetensors`` (safetensors: no
pickle, each tensor read by memory map without loading the shard) holding, for each training sample ``i`` and each
augmentation draw ``d`` it is seen under, the teacher's value of every tap the stage's terms read, computed on that
sample alone — ``i:d:TAP:value`` for a dense tap (its batch row), ``:coords`` and ``:feats`` for sparse features
(the rows of the sample, without the batch column), ``:points`` for a point cloud (its ``lengths`` points); and
``manifest.json``: the key and what it was computed from, the taps and their kinds, the sparse taps' grids, the
sample ids in split order, the number of draws, and each shard's samples, bytes and SHA-256. A shard is written to a
temporary name and renamed, with a ``.json`` beside it (its bytes and checksum), so an interrupted build keeps every
finished shard and a truncated or altered one is found by its checksum and named.

The values a batch reads are the stored rows stacked (dense taps) or concatenated with their batch column (sparse
features, in batch order, as the live teacher's batched output is) — the same bits as the live teacher's batched
forward wherever that forward computes each sample independently of the others (checked for every built-in teacher
by the exactness test).

Lossy layouts (:class:`~distilkit.recipe.store.StoreSpec`), opt-in: a narrower ``precision`` (every floating value
stored as float16 or bfloat16 and read back in the teacher's type); ``voxels`` (a dense tap on the labels' grid
keeps the voxels of the mask, ``i:d:@voxels:index`` their flat indices, ``:value`` their (C, n) values; the others
read back as 0); ``topk`` (a ``voxel_logits`` tap keeps ``:top`` the k largest scores of each voxel, ``:class``
their classes and ``:lse`` the logsumexp of all C: on reading, the other C - k classes share the remaining
probability mass evenly, so the softmax at temperature 1 is exact on the k classes and on the rest's total).
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from distilkit.errors import DataError
from distilkit.structures import PointCloud, SparseVoxels, VoxelGrid
from distilkit.taps import DENSE_GRID_KINDS as GRID_KINDS

FORMAT = 1
MANIFEST = "manifest.json"


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def shard_name(index: int) -> str:
    return f"shard-{index:05d}.safetensors"




def _narrow(t: Tensor, precision: torch.dtype) -> Tensor:
    return t.to(precision) if t.is_floating_point() else t


def _own(t: Tensor) -> Tensor:  # contiguous, in memory of its own (two taps may view one tensor)
    return t.detach().cpu().clone(memory_format=torch.contiguous_format)


def _masked(value: Any, kind: str, grid: tuple[int, ...] | None) -> bool:
    """Whether a tap's value (a batch of one) is kept at a mask's voxels: a dense tap on the mask's (X, Y, Z) grid
    (None: no mask)."""
    return grid is not None and kind in GRID_KINDS and isinstance(value, Tensor) and value.dim() == 5 and \
        tuple(value.shape[2:]) == tuple(grid)


def _grid(mask: Tensor | None) -> tuple[int, ...] | None:
    return None if mask is None else tuple(mask.shape)


def _dense(value: Tensor, kind: str, prefix: str, mask: Tensor | None, topk: int | None,
           precision: torch.dtype) -> dict[str, Tensor]:
    """One sample's row of a dense tap in the layout: whole, or its masked voxels, or its top-k classes."""
    v = value.float() if value.is_floating_point() else value
    if _masked(value[None], kind, _grid(mask)):
        v = v.flatten(1)[:, mask.flatten()]  # (C, n)
    if topk is not None and kind == "voxel_logits" and topk < v.shape[0]:
        top, cls = v.topk(topk, dim=0)
        return {f"{prefix}:top": _own(_narrow(top, precision)), f"{prefix}:class": _own(cls.to(torch.int16)),
                f"{prefix}:lse": _own(_narrow(torch.logsumexp(v, dim=0, keepdim=True), precision))}
    return {f"{prefix}:value": _own(_narrow(v, precision))}


def sample_tensors(outputs: dict[str, Any], taps: dict[str, str], prefix: str, *, mask: Tensor | None = None,
                   topk: int | None = None, precision: torch.dtype = torch.float32) -> dict[str, Tensor]:
    """The tensors to store of one sample's teacher outputs (a batch of one), named ``prefix:TAP:part``, in the
    layout: ``mask`` the (X, Y, Z) voxels kept of dense taps on that grid (None: all), ``topk`` the classes kept of
    ``voxel_logits`` taps, ``precision`` the floating values' type."""
    out: dict[str, Tensor] = {}
    for tap, kind in taps.items():
        value = outputs[tap]
        if isinstance(value, SparseVoxels):
            out[f"{prefix}:{tap}:coords"] = _own(value.coords[:, 1:])
            out[f"{prefix}:{tap}:feats"] = _own(_narrow(value.feats.float(), precision))
        elif isinstance(value, PointCloud):
            out[f"{prefix}:{tap}:points"] = _own(_narrow(value.points[0, : int(value.lengths[0])].float(), precision))
        elif isinstance(value, Tensor) and value.dim() >= 1 and value.shape[0] == 1:
            out.update(_dense(value[0], kind, f"{prefix}:{tap}", mask, topk, precision))
        else:
            raise DataError(f"teacher tap {tap!r} ({type(value).__name__}) has no per-sample rows to store")
    if any(_masked(outputs[tap], kind, _grid(mask)) for tap, kind in taps.items()):  # the kept voxels, once a sample
        out[f"{prefix}:@voxels:index"] = _own(mask.flatten().nonzero()[:, 0].to(torch.int32))
    return out


def _read_dense(shard: Any, prefix: str, tap: str, meta: dict[str, Any]) -> Tensor:
    """One sample's row of a dense tap, back in its shape and type from any layout (see the module)."""
    dtype = getattr(torch, meta.get("dtype", "float32"))
    if meta.get("topk"):
        top = shard.get_tensor(f"{prefix}:{tap}:top").float()
        cls = shard.get_tensor(f"{prefix}:{tap}:class").long()
        lse = shard.get_tensor(f"{prefix}:{tap}:lse").float()
        classes, k = int(meta["shape"][0]), top.shape[0]
        kept = torch.exp(top - lse).sum(0, keepdim=True).clamp(max=1.0)
        rest = lse + torch.log1p(-kept).clamp(min=-80.0) - math.log(classes - k)  # the rest's mass, shared evenly
        v = rest.expand(classes, *top.shape[1:]).clone().scatter_(0, cls, top)
    else:
        v = shard.get_tensor(f"{prefix}:{tap}:value")
    if meta.get("masked"):
        full = torch.zeros(v.shape[0], math.prod(meta["shape"][1:]), dtype=v.dtype)
        full[:, shard.get_tensor(f"{prefix}:@voxels:index").long()] = v
        v = full.view(meta["shape"])
    return v.to(dtype) if v.is_floating_point() else v


def batch_difference(batched: dict[str, Any], singles: list[dict[str, Any]], taps: dict[str, str]) -> tuple[float, str]:
    """The largest difference between a teacher's output on a batch and its outputs on each sample alone (what a
    store holds), and the tap where it is: 0 where the forward computes each sample independently of the others
    (inf where the rows themselves differ)."""
    worst, where = 0.0, ""
    for tap in taps:
        together = batched[tap]
        for b, alone in enumerate(singles):
            a = alone[tap]
            if isinstance(together, SparseVoxels):
                rows = together.coords[:, 0] == b
                same = torch.equal(together.coords[rows, 1:], a.coords[:, 1:])
                diff = (together.feats[rows].float() - a.feats.float()).abs().max().item() if same and len(a.feats) \
                    else (0.0 if same else float("inf"))
            elif isinstance(together, PointCloud):
                n = int(together.lengths[b])
                diff = (together.points[b, :n].float() - a.points[0, :n].float()).abs().max().item() \
                    if n == int(a.lengths[0]) else float("inf")
            else:
                diff = (together[b].float() - a[0].float()).abs().max().item()
            if diff > worst:
                worst, where = diff, tap
    return worst, where


def tap_layout(outputs: dict[str, Any], taps: dict[str, str], mask_shape: tuple[int, ...] | None = None,
               topk: int | None = None) -> dict[str, Any]:
    """What the manifest keeps of each tap beside its kind: a sparse tap's grid; a dense tap's per-sample shape,
    type, and whether it is stored masked (on the grid ``mask_shape``) or by its top-k classes."""
    out: dict[str, Any] = {}
    for tap, kind in taps.items():
        value = outputs[tap]
        entry: dict[str, Any] = {"kind": kind}
        if isinstance(value, Tensor) and not isinstance(value, (SparseVoxels, PointCloud)):
            row = value[0]
            entry.update(shape=list(row.shape), dtype=str(row.dtype).removeprefix("torch."),
                         masked=_masked(value, kind, mask_shape),
                         topk=topk if topk is not None and kind == "voxel_logits" and topk < row.shape[0] else None)
        if isinstance(value, SparseVoxels):
            entry["spatial_shape"] = list(value.spatial_shape)
            if value.grid is not None:
                entry["grid"] = {"origin": list(value.grid.origin), "shape": list(value.grid.shape),
                                 "voxel_size": value.grid.voxel_size}
        out[tap] = entry
    return out


def write_shard(folder: Path, index: int, tensors: dict[str, Tensor], extra: dict[str, Any]) -> dict[str, Any]:
    """Shard ``index`` written whole under a temporary name, then renamed, with its ``.json`` (bytes, SHA-256 and
    ``extra``: its sample count and the taps' layout, so a resumed build needs nothing it did not write)."""
    import os
    import tempfile

    from safetensors.torch import save_file

    from distilkit.files import atomic_write_text

    target = folder / shard_name(index)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{target.name}.")  # a name of its own: two builders never share
    os.close(fd)
    try:
        save_file(tensors, tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    entry = {"file": target.name, "bytes": target.stat().st_size, "sha256": file_sha256(target), **extra}
    atomic_write_text(target.with_suffix(".json"), json.dumps(entry))
    return entry


def finished_shard(folder: Path, index: int) -> dict[str, Any] | None:
    """Shard ``index``'s record where the file is whole (its bytes and checksum those its ``.json`` recorded)."""
    target = folder / shard_name(index)
    record = target.with_suffix(".json")
    if not target.is_file() or not record.is_file():
        return None
    try:
        entry = json.loads(record.read_text(encoding="utf-8"))
    except ValueError:
        return None
    if target.stat().st_size != entry.get("bytes") or file_sha256(target) != entry.get("sha256"):
        return None
    return dict(entry)


def whole(folder: Path) -> bool:
    """Whether a store's manifest is there and every shard it lists is there at its size (checksums: on reading)."""
    try:
        manifest = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
        return all((folder / e["file"]).is_file() and (folder / e["file"]).stat().st_size == e["bytes"]
                   for e in manifest["shards"])
    except (OSError, ValueError, KeyError, TypeError):
        return False


class TeacherOutputs:
    """A finished store, read by the samples' ids and draws of a batch (:meth:`batch`)."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        path = self.folder / MANIFEST
        try:
            self.manifest = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise DataError(f"{path}: not a teacher store's manifest ({exc})") from None
        if self.manifest.get("format") != FORMAT:
            raise DataError(f"{path}: store format {self.manifest.get('format')!r}, this distilkit reads {FORMAT}")
        self.taps: dict[str, Any] = self.manifest["taps"]
        self.index = {sid: i for i, sid in enumerate(self.manifest["samples"])}
        self.per_shard = int(self.manifest["shard"])
        self._open: dict[int, Any] = {}

    def __getstate__(self) -> dict[str, Any]:  # to a loader worker: the open shards stay here
        return {**self.__dict__, "_open": {}}

    def _shard(self, i: int) -> Any:
        from safetensors import safe_open

        s = i // self.per_shard
        if s not in self._open:
            entry = self.manifest["shards"][s]
            path = self.folder / entry["file"]
            if not path.is_file() or path.stat().st_size != entry["bytes"] or file_sha256(path) != entry["sha256"]:
                raise DataError(f"{path}: the teacher store's shard is missing, truncated or altered (its checksum "
                                f"is not the manifest's); delete it and run the stage again: the build redoes that "
                                f"shard alone")
            self._open[s] = safe_open(str(path), framework="pt")
        return self._open[s]

    def of(self, batch: Any, device: torch.device, rename: dict[str, str] | None = None) -> dict[str, Any]:
        """:meth:`batch` for a collated batch: its samples' ids under their augmentation draws (0: none); with
        ``rename``, each id read at the id it maps to (a shuffled control's partner), the others at their own."""
        draws = batch.meta.get("augment_draw") or [0] * batch.size
        ids = [str(s) for s in batch.meta.get("sample_id", ())]
        return self.batch([rename.get(s, s) for s in ids] if rename else ids, list(draws), device)

    def batch(self, sample_ids: list[str], draws: list[int], device: torch.device) -> dict[str, Any]:
        """Every stored tap of a batch: the samples' rows under their draws, assembled as the teacher returns them."""
        rows = []
        for sid, d in zip(sample_ids, draws):
            if sid not in self.index:
                raise DataError(f"{self.folder}: sample {sid!r} is not in the teacher store (built for another split "
                                "or data)")
            rows.append((self._shard(self.index[sid]), f"{self.index[sid]}:{int(d)}"))
        out: dict[str, Any] = {}
        for tap, meta in self.taps.items():
            if meta.get("spatial_shape") is not None:
                coords, feats = [], []
                for b, (shard, prefix) in enumerate(rows):
                    c = shard.get_tensor(f"{prefix}:{tap}:coords")
                    coords.append(torch.cat([torch.full((len(c), 1), b, dtype=c.dtype), c], dim=1))
                    feats.append(shard.get_tensor(f"{prefix}:{tap}:feats"))
                grid = meta.get("grid")
                out[tap] = SparseVoxels(torch.cat(coords).to(device), torch.cat(feats).to(device),
                                        tuple(meta["spatial_shape"]),
                                        VoxelGrid(tuple(grid["origin"]), tuple(grid["shape"]), grid["voxel_size"])
                                        if grid else None)
            elif meta["kind"] == "points":
                out[tap] = PointCloud.from_list([shard.get_tensor(f"{prefix}:{tap}:points").to(device)
                                                 for shard, prefix in rows])
            else:
                out[tap] = torch.stack([_read_dense(shard, prefix, tap, meta) for shard, prefix in rows]).to(device)
        return out


class WithTeacherOutputs:
    """A training collate that also reads each batch's stored teacher rows (into ``batch.meta["teacher_outputs"]``,
    on the CPU), so that a loader's workers read the store while the student computes (``train.workers``)."""

    def __init__(self, collate: Any, store: TeacherOutputs) -> None:
        self.collate, self.store = collate, store

    def __call__(self, samples: list[Any]) -> Any:
        batch = self.collate(samples)
        batch.meta["teacher_outputs"] = self.store.of(batch, torch.device("cpu"))
        return batch


def to_device(value: Any, device: torch.device) -> Any:
    """A tap's value (tensor, sparse voxels, point cloud) on ``device``."""
    if isinstance(value, PointCloud):
        return PointCloud(value.points.to(device), value.lengths.to(device))
    return value.to(device) if isinstance(value, (Tensor, SparseVoxels)) else value


__all__ = ["FORMAT", "WithTeacherOutputs", "to_device", "MANIFEST", "TeacherOutputs", "batch_difference", "file_sha256", "finished_shard",
           "sample_tensors", "shard_name", "tap_layout", "whole", "write_shard"]
