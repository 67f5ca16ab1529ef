"""Which taps of a student and a teacher can be paired, by kind (torch-free): logits on one grid; sparse features
on grids in an integer ratio (matched voxel by voxel: a coarser teacher read at the parent voxel, a finer one
pooled); dense maps of one refinement (volume with volume, bird's-eye with bird's-eye, image with image) on one
grid, or on grids in an integer ratio for the terms that resize; image features of one camera. Points pair by the
models' capabilities, not by taps (see :mod:`distilkit.pairing.fit`)."""

from __future__ import annotations

from dataclasses import dataclass

from distilkit.geometry.grids import grid_factors, plane_factors
from distilkit.pairing.facts import ModelFacts, TapFact

KIND_ORDER = ("voxel_logits", "sparse_features", "volume_features", "bev_features", "image_features")
PLANE = "bev_features"


@dataclass(frozen=True)
class TapPair:
    """A student tap and a teacher tap of one kind; ``how`` they align: ``same`` (one grid or shape), ``teacher
    coarser xF``/``teacher finer xF`` (the teacher's grid F times coarser or finer; ``x2x2x1`` per axis where the
    factors differ), ``resized`` (image maps of other sizes), ``collapsed`` (a student's bird's-eye map against the
    teacher's voxels on its plane)."""

    student: TapFact
    teacher: TapFact
    kind: str
    how: str

    @property
    def same(self) -> bool:
        """Whether both taps are on one grid (or of one shape)."""
        return self.how == "same"

    def text(self) -> str:
        """The pair in one line: taps, kind, sizes, how they align, channels."""
        if self.how == "collapsed":
            return (f"{self.student.tap} <- {self.teacher.tap}: the teacher's voxels collapsed onto the student's "
                    f"{self.student.size()} plane")
        cs, ct = self.student.channels, self.teacher.channels
        widths = f"{cs if cs is not None else '?'} <- {ct if ct is not None else '?'} ch"
        return (f"{self.student.tap} <- {self.teacher.tap}: {self.kind}, {self.student.size()} <- "
                f"{self.teacher.size()} ({self.how}), {widths}")


def _factors(how: tuple[str, tuple[int, ...]] | str) -> str | None:
    if isinstance(how, str):
        return None
    kind, f = how
    return "same" if kind == "same" else f"teacher {kind} x{'x'.join(map(str, f)) if len(set(f)) > 1 else f[0]}"


def align(s: TapFact, t: TapFact) -> str | None:
    """How tap ``t`` (the teacher's) aligns with ``s`` (the student's), or None where it cannot."""
    if s.kind == PLANE and t.kind == "sparse_features":  # a map against voxels it collapses (voxel-to-BEV)
        if s.grid is None or t.grid is None or t.of is not None:
            return None
        how = plane_factors(s.grid, t.grid)
        return "collapsed" if not isinstance(how, str) and how[0] == "same" else None
    if s.kind != t.kind or s.kind not in KIND_ORDER:
        return None
    if s.kind == "image_features":
        if s.camera is not None and t.camera is not None and s.camera != t.camera:
            return None
        return "same" if s.shape == t.shape else "resized"
    if s.grid is not None and t.grid is not None:
        how = _factors(plane_factors(s.grid, t.grid) if s.kind == PLANE else grid_factors(s.grid, t.grid))
    elif s.shape is not None and t.shape is not None and len(s.shape) == len(t.shape):
        how = _factors(grid_factors(tuple(s.shape), tuple(t.shape)))
    else:
        return None
    if how is None:
        return None
    if s.kind == "voxel_logits" and how != "same":
        return None  # logits are compared voxel by voxel on one grid
    return how


def tap_pairs(student: ModelFacts, teacher: ModelFacts) -> list[TapPair]:
    """Every pair that aligns, best first: by kind (logits, sparse, volume, bird's-eye, image), then one grid before
    an integer ratio, then the taps' declaration order."""
    out = []
    for s in student.taps:
        for t in teacher.taps:
            how = align(s, t) if s.present and t.present else None
            if how is not None:
                out.append(TapPair(s, t, s.kind, how))
    order = {t.tap: i for i, t in enumerate(student.taps)}
    t_order = {t.tap: i for i, t in enumerate(teacher.taps)}
    return sorted(out, key=lambda p: (KIND_ORDER.index(p.kind), p.how == "collapsed", not p.same,
                                      order[p.student.tap],
                                      t_order[p.teacher.tap]))


__all__ = ["KIND_ORDER", "TapPair", "align", "tap_pairs"]
