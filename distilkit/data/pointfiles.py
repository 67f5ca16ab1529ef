"""Point-cloud files a user brings: SemanticKITTI ``.bin`` (float32 x, y, z, intensity), ``.npy`` ((N, >=3) array)
and ``.ply`` (ascii or binary, vertex x/y/z; read here, no dependency), and ``.ply``/``.npy``/``.bin`` written back.
A malformed file gets one :class:`~distilkit.errors.DataError` naming it and what is wrong."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from distilkit.errors import DataError

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
              "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
              "double": "f8", "float64": "f8"}


def _read_ply(path: Path) -> np.ndarray:
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise DataError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header')")
    body = data[data.index(b"\n", end) + 1:]
    fmt, count, props, in_vertex = None, 0, [], False
    for line in data[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if not words:
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3:
                raise DataError(f"{path}: PLY header line {line.strip()!r}: expected 'element NAME COUNT'")
            in_vertex = words[1] == "vertex"
            if in_vertex:
                if not words[2].isdigit():
                    raise DataError(f"{path}: PLY header 'element vertex {words[2]}': the vertex count must be a "
                                    "whole number >= 0")
                count = int(words[2])
            elif not props:  # an element before the vertices would have to be skipped: not supported
                raise DataError(f"{path}: PLY elements before 'vertex' are not supported")
        elif words[0] == "property" and in_vertex:
            if len(words) < 3:
                raise DataError(f"{path}: PLY header line {line.strip()!r}: expected 'property TYPE NAME'")
            if words[1] == "list":
                raise DataError(f"{path}: list properties on vertices are not supported")
            if words[1] not in _PLY_TYPES:
                raise DataError(f"{path}: unknown PLY property type {words[1]!r}")
            props.append((words[2], _PLY_TYPES[words[1]]))
    names = [n for n, _ in props]
    if not {"x", "y", "z"} <= set(names):
        raise DataError(f"{path}: the PLY vertices have no x, y, z properties (they have: {', '.join(names) or 'none'})")
    if fmt == "ascii":
        rows = body.decode("ascii", "replace").split("\n")[:count]
        try:
            table = np.array([[float(v) for v in r.split()[: len(props)]] for r in rows], dtype=np.float64)
        except ValueError as exc:
            raise DataError(f"{path}: unreadable ASCII PLY vertex row ({exc})") from None
        if table.shape != (count, len(props)):
            raise DataError(f"{path}: expected {count} vertex rows of {len(props)} values")
        return table[:, [names.index(a) for a in "xyz"]].astype(np.float32)
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise DataError(f"{path}: unknown PLY format {fmt!r}")
    order = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(n, order + t) for n, t in props])
    if len(body) < count * dtype.itemsize:
        raise DataError(f"{path}: truncated PLY ({len(body)} bytes of vertex data, {count * dtype.itemsize} expected)")
    vertices = np.frombuffer(body, dtype=dtype, count=count)
    return np.stack([vertices[a].astype(np.float32) for a in "xyz"], axis=1)


def read_points(path: str | Path) -> np.ndarray:
    """(N, 3) float32 points of a ``.bin``, ``.npy`` or ``.ply`` file."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".bin":
        raw = path.read_bytes()
        if len(raw) % 16:
            raise DataError(f"{path}: {len(raw)} bytes is not a whole number of SemanticKITTI points "
                            "(float32 x, y, z, intensity = 16 bytes each)")
        points = np.frombuffer(raw, dtype="<f4").reshape(-1, 4)[:, :3]
    elif suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as exc:
            raise DataError(f"{path}: not a readable .npy array ({type(exc).__name__}: {exc})") from None
        if arr.ndim != 2 or arr.shape[1] < 3 or not np.issubdtype(arr.dtype, np.number):
            raise DataError(f"{path}: expected an (N, 3+) numeric array, got {arr.shape} {arr.dtype}")
        points = arr[:, :3]
    elif suffix == ".ply":
        points = _read_ply(path)
    else:
        raise DataError(f"{path}: unknown point-cloud format {suffix!r} (use .bin, .npy or .ply)")
    points = np.ascontiguousarray(points, dtype=np.float32)
    if len(points) == 0:
        raise DataError(f"{path}: the file holds no point")
    return check_finite(points, path)


def check_finite(points: np.ndarray, path: str | Path) -> np.ndarray:
    """``points`` if every coordinate is finite, else a DataError naming the file and how many points are not (one
    rule for every reader: a user's scan for ``distilkit complete`` and a SemanticKITTI folder's scans alike)."""
    bad = ~np.isfinite(points[:, :3]).all(axis=1)
    if bad.any():
        raise DataError(f"{path}: {int(bad.sum())} of {len(points)} points have non-finite coordinates (NaN or inf; "
                        f"the first is point {int(np.argmax(bad))})")
    return points


def write_points(path: str | Path, points: np.ndarray) -> Path:
    """Write (N, 3) points as binary little-endian ``.ply``, ``.npy`` or SemanticKITTI ``.bin`` (intensity 0)."""
    path = Path(path).expanduser()
    pts = np.ascontiguousarray(points[:, :3], dtype="<f4")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    suffix = path.suffix.lower()
    if suffix == ".ply":
        header = (f"ply\nformat binary_little_endian 1.0\ncomment distilkit completion\nelement vertex {len(pts)}\n"
                  "property float x\nproperty float y\nproperty float z\nend_header\n")
        tmp.write_bytes(header.encode("ascii") + pts.tobytes())
    elif suffix == ".npy":
        with open(tmp, "wb") as f:
            np.save(f, pts)
    elif suffix == ".bin":
        tmp.write_bytes(np.concatenate([pts, np.zeros((len(pts), 1), "<f4")], axis=1).tobytes())
    else:
        raise DataError(f"{path}: unknown output format {suffix!r} (use .ply, .npy or .bin)")
    tmp.replace(path)
    return path


__all__ = ["check_finite", "read_points", "write_points"]
