"""Cell validity and mesh-quality measures for P1 simplex meshes.

Everything here is vectorised with numpy over all cells at once; there is
no Python loop per cell or per vertex.

Conventions
-----------
* ``x`` is a geometry array of shape ``(n, 3)`` (as ``mesh.geometry.x``;
  in 2D the third column is ignored), in the length unit of the mesh.
* ``cells`` is an integer array of shape ``(nc, tdim + 1)`` of indices into
  ``x`` (as ``mesh.geometry.dofmaps[0]`` for a P1 mesh).
* ``gdim`` is the geometric dimension, 2 (triangles) or 3 (tetrahedra).
  The topological dimension is taken from ``cells.shape[1] - 1`` and must
  equal ``gdim``.

The geometric kernels (signed volumes, edge vectors, the local edge
tables) are those of :mod:`nagata_snap.mesh.simplex`; this module builds
the validity checks and shape measures on them.

Quality measures (all dimensionless, 1 for the equilateral triangle /
regular tetrahedron, tending to 0 for degenerate cells):

* radius ratio ``rho = d * r_in / R_circ`` (``d`` = dimension); the inverse
  ``1 / rho = R / (d r)`` is the ">= 1" convention used e.g. by Kadir 2010.
* mean ratio ``q = d * |K|^(2/d) / (c_d * sum_edges l^2)`` normalised so
  that ``q = 1`` for the regular simplex (2D: ``4 sqrt(3) |K| / sum l^2``,
  3D: ``12 (3 |K|)^(2/3) / sum l^2``).
* angles in degrees: the three interior angles of a triangle, the six
  dihedral angles of a tetrahedron.

MPI
---
:class:`QualityReport` reduces over ranks using owned cells (and owned
geometry nodes) only, so every rank holds and prints identical numbers.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import operator
from typing import Any

import dolfinx.mesh
import mpi4py.MPI
import numpy as np

from nagata_snap.mesh.arrays import dot
from nagata_snap.mesh.simplex import (
    TET_EDGE_FACETS,
    cell_columns,
    cell_dim,
    cells_touching,
    cross,
    edge_components,
    edge_length_range,
    signed_volumes,
    signed_volumes_of,
    vertex_components,
)
from nagata_snap.smoothing import kernels

__all__ = [
    "degenerate_cells",
    "inverted_cells",
    "inverted_mask",
    "quality_stats",
    "mean_ratio",
    "MetricSummary",
    "QualityReport",
    "ANGLE_BINS",
    "RATIO_BINS",
]

#: Fixed histogram bin edges (degrees) for minimum / maximum angles.
ANGLE_BINS = np.array([0.0, 5.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 75.0,
                       90.0, 120.0, 150.0, 180.0])
#: Fixed histogram bin edges for the radius ratio and the mean ratio.
RATIO_BINS = np.array([0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8,
                       0.9, 1.0])


def inverted_mask(v_new: np.ndarray, v_ref: np.ndarray, rel_floor: float) -> np.ndarray:
    """``(nc,)`` bool: cells inverted or collapsed, from signed volumes ``v_new``, ``v_ref`` ``(nc,)``.

    The criterion of :func:`inverted_cells`:
    ``v_new * sign(v_ref) <= rel_floor * |v_ref|``.
    """
    return v_new * np.sign(v_ref) <= rel_floor * np.abs(v_ref)


def degenerate_cells(x: np.ndarray, cells: np.ndarray, gdim: int,
                     rel_floor: float = 1e-12) -> np.ndarray:
    """Cells whose measure is at most ``rel_floor`` times (longest edge)^gdim.

    Such a cell has no usable orientation or shape (zero area / volume, or
    round-off away from it).

    Args:
        x: (n, 3) node coordinates; cells: (nc, gdim + 1) node indices per cell.
        gdim: 2 or 3; rel_floor: dimensionless threshold (>= 0).

    Returns:
        (m,) int32 indices into ``cells`` (sorted ascending).
    """
    _, hmax = edge_length_range(x, cells, gdim)
    vol = np.abs(signed_volumes(x, cells, gdim))
    return np.flatnonzero(vol <= rel_floor * hmax**gdim).astype(np.int32)


def inverted_cells(x_new: np.ndarray, x_ref: np.ndarray, cells: np.ndarray,
                   gdim: int, rel_floor: float = 1e-12) -> np.ndarray:
    """Cells that are inverted (or collapsed) in ``x_new`` relative to ``x_ref``.

    A cell ``K`` is reported when
    ``vol_new(K) * sign(vol_ref(K)) <= rel_floor * |vol_ref(K)|``, i.e. its
    signed volume changed sign, or shrank to at most ``rel_floor`` times its
    reference volume. Cells that are degenerate in the reference (zero
    volume) are always reported.

    Args:
        x_new: (n, 3) node coordinates to check.
        x_ref: (n, 3) reference coordinates (the straight refined mesh, which
            carries the orientation of the parent cells).
        cells: (nc, gdim + 1) int array of node indices per cell.
        gdim: 2 or 3.
        rel_floor: dimensionless relative volume floor (>= 0).

    Returns:
        (m,) int32 array of indices into ``cells`` (sorted ascending).
    """
    v_new = signed_volumes(x_new, cells, gdim)
    v_ref = signed_volumes(x_ref, cells, gdim)
    return np.flatnonzero(inverted_mask(v_new, v_ref, rel_floor)).astype(np.int32)


def _mean_ratio_of(avol: np.ndarray, l2sum: np.ndarray, gdim: int) -> np.ndarray:
    """Mean ratio ``(nc,)`` from the unsigned measures and the sums of squared edge lengths."""
    with np.errstate(divide="ignore", invalid="ignore"):
        if gdim == 2:
            q = 4.0 * math.sqrt(3.0) * avol / l2sum
        else:
            q = 12.0 * np.cbrt(3.0 * avol) ** 2 / l2sum
    return np.minimum(np.where(np.isfinite(q), q, 0.0), 1.0)


def mean_ratio(x: np.ndarray, cells: np.ndarray, gdim: int) -> np.ndarray:
    """Normalised mean ratio of every cell (cheap; no angles).

    Args:
        x: (n, 3) node coordinates.
        cells: (nc, gdim + 1) int node indices per cell.
        gdim: 2 or 3.

    Returns:
        (nc,) float64 in [0, 1], 1 for the equilateral triangle / regular
        tetrahedron, 0 for degenerate cells (orientation is ignored).
    """
    cell_dim(cells, gdim)
    P = vertex_components(x, cells, gdim)
    l2sum = functools.reduce(operator.add, [dot(e, e) for e in edge_components(P)])
    return _mean_ratio_of(np.abs(signed_volumes_of(P)), l2sum, gdim)


def _triangle_shapes(ev: list[list[np.ndarray]], l2: list[np.ndarray], avol: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(min angle, max angle, radius ratio)`` of triangles (radians; three ``(nc,)`` arrays).

    ``ev``: the edge vectors (:func:`~nagata_snap.mesh.simplex.edge_components`),
    ``l2`` their squared lengths, ``avol`` the unsigned areas.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        # interior angles: |e_a x e_b| = 2|A| for any two edges, so
        # angle_k = atan2(2|A|, dot of the two edges leaving vertex k)
        e01, e02, e12 = ev
        twoA = 2.0 * avol
        ang = [np.arctan2(twoA, dot(e01, e02)),
               np.arctan2(twoA, -dot(e01, e12)),
               np.arctan2(twoA, dot(e02, e12))]
        amin = np.minimum(np.minimum(ang[0], ang[1]), ang[2])
        amax = np.maximum(np.maximum(ang[0], ang[1]), ang[2])
        la, lb, lc = np.sqrt(l2[0]), np.sqrt(l2[1]), np.sqrt(l2[2])
        # 2 r / R = 16 A^2 / (perimeter * a b c)
        rr = 16.0 * avol * avol / ((la + lb + lc) * (la * lb * lc))
        rr = np.where(np.isfinite(rr), rr, 0.0)
    return amin, amax, rr


def _tetrahedron_shapes(ev: list[list[np.ndarray]], l2: list[np.ndarray], vol: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(min dihedral angle, max dihedral angle, radius ratio)`` of tetrahedra (radians).

    The numpy reference of :func:`~nagata_snap.smoothing.kernels.tet_shapes`,
    which :func:`quality_stats` calls (``tests/test_kernels.py`` compares them).

    ``ev``: the six edge vectors (:data:`~nagata_snap.mesh.simplex.TET_EDGES`
    order), ``l2`` their squared lengths, ``vol`` the signed volumes.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        e1, e2, e3 = ev[0], ev[1], ev[2]  # edges 01, 02, 03
        # cofactor vectors: det(J) * grad(lambda_k); all scaled by the
        # same factor, so their mutual angles equal those between the
        # inward face normals, also for inverted / flat cells.
        c1, c2, c3 = cross(e2, e3), cross(e3, e1), cross(e1, e2)
        c0 = [-(a + b + c) for a, b, c in zip(c1, c2, c3, strict=True)]
        cof = [c0, c1, c2, c3]
        nrm = [np.sqrt(dot(c, c)) for c in cof]  # 2 * face areas
        # The dihedral angle at the edge shared by faces fa, fb is
        # pi - angle(cof[fa], cof[fb]), an increasing function of the
        # cosine of that angle: the min / max dihedral angles come from
        # the min / max cosine over the six edges (two arccos per cell
        # instead of six cross products and arctan2). A zero-area face
        # counts as cosine 1 (dihedral angle pi).
        cos = []
        for fa, fb in TET_EDGE_FACETS:
            den = nrm[fa] * nrm[fb]
            cos.append(np.divide(dot(cof[fa], cof[fb]), den, out=np.ones_like(den), where=den > 0))
        amin = np.pi - np.arccos(np.clip(np.minimum.reduce(cos), -1.0, 1.0))
        amax = np.pi - np.arccos(np.clip(np.maximum.reduce(cos), -1.0, 1.0))
        # 3 r / R = 216 V^2 / (S * sqrt(P)),  r = 3V/S,
        # R = sqrt(P) / (24 V),  P from products of opposite edges
        S = 0.5 * (nrm[0] + nrm[1] + nrm[2] + nrm[3])
        le = [np.sqrt(v) for v in l2]
        # opposite edge pairs: (01,23), (02,13), (03,12)
        a = le[0] * le[5]
        b = le[1] * le[4]
        c = le[2] * le[3]
        Pp = (a + b + c) * (a + b - c) * (a - b + c) * (-a + b + c)
        rr = 216.0 * vol**2 / (S * np.sqrt(np.maximum(Pp, 0.0)))
        rr = np.where(np.isfinite(rr), rr, 0.0)
    return amin, amax, rr


def quality_stats(x: np.ndarray, cells: np.ndarray, gdim: int,
                  orientation: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Per-cell shape measures.

    Args:
        x: (n, 3) node coordinates.
        cells: (nc, gdim + 1) int node indices per cell.
        gdim: 2 (triangle angles) or 3 (dihedral angles).
        orientation: optional (nc,) array whose sign gives the expected
            orientation of each cell (e.g. the reference signed volumes).
            When given, the ratio measures of cells whose signed volume has
            the other sign (or is zero) are returned negated (<= 0), so that
            inverted cells cannot look good.

    Returns:
        dict of (nc,) float64 arrays:

        * ``"volume"``: signed area / volume (L^2 / L^3),
        * ``"min_angle"``, ``"max_angle"``: degrees; interior angles of
          triangles (60 for equilateral) or dihedral angles of tetrahedra
          (arccos(1/3) = 70.53 for the regular tetrahedron),
        * ``"radius_ratio"``: ``d r_in / R_circ`` in [0, 1],
        * ``"mean_ratio"``: normalised mean ratio in [0, 1].
    """
    tdim = cell_dim(cells, gdim)
    if tdim == 3:  # the compiled kernel of _tetrahedron_shapes' formulas
        vol, amin, amax, rr, l2sum = kernels.tet_shapes(
            np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(cells, dtype=np.int64))
    else:
        P = vertex_components(x, cells, gdim)
        vol = signed_volumes_of(P)
        ev = edge_components(P)
        l2 = [dot(e, e) for e in ev]  # squared edge lengths
        amin, amax, rr = _triangle_shapes(ev, l2, np.abs(vol))
        l2sum = functools.reduce(operator.add, l2)
    q = {
        "volume": vol,
        "min_angle": np.degrees(amin),
        "max_angle": np.degrees(amax),
        "radius_ratio": np.minimum(rr, 1.0),  # round-off guard for (near-)regular cells
        "mean_ratio": _mean_ratio_of(np.abs(vol), l2sum, gdim),
    }
    if orientation is not None:
        _orient(q, orientation)
    return q


def _orient(q: dict[str, np.ndarray], orientation: np.ndarray) -> None:
    """Negate (in ``q``) the ratios of cells whose volume sign differs from ``orientation``."""
    good = q["volume"] * np.sign(np.asarray(orientation, dtype=np.float64)) > 0
    for k in ("radius_ratio", "mean_ratio"):
        q[k] = np.where(good, q[k], -q[k])


# ---------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------


class _Reference:
    """The reference coordinates of a report: which nodes moved, and the reference volumes.

    Args:
        x_new: ``(n, 3)`` coordinates assessed; x_ref: ``(n, 3)`` reference
            coordinates; x_before: ``(n, 3)`` coordinates before smoothing, or None.

    Attributes:
        moved_new, moved_before: ``(n,)`` bool, nodes off ``x_ref`` in
            ``x_new`` / ``x_before`` (``moved_before`` None without ``x_before``);
        changed: ``(n,)`` bool, their union.
        v_ref, v_before: ``(nc,)`` signed volumes of the report's cells in
            ``x_ref`` / ``x_before``, after :meth:`volumes`.
    """

    def __init__(self, x_new: np.ndarray, x_ref: np.ndarray, x_before: np.ndarray | None):
        # nodes moved off x_ref, once per coordinate array (O(nodes))
        self.x_ref = np.asarray(x_ref, dtype=np.float64)
        self.moved_new = np.any(x_new != self.x_ref, axis=1)
        self.x_before = None if x_before is None else np.asarray(x_before, dtype=np.float64)
        self.moved_before = None
        self.changed = self.moved_new
        if self.x_before is not None:
            self.moved_before = np.any(self.x_before != self.x_ref, axis=1)
            self.changed = self.moved_new | self.moved_before
        self.v_ref: np.ndarray | None = None
        self.v_before: np.ndarray | None = None

    def volumes(self, cells: np.ndarray, v_new: np.ndarray, gdim: int) -> np.ndarray:
        """Set (and return) ``v_ref``, and ``v_before``, of ``cells``, whose volumes in ``x_new`` are ``v_new``.

        A cell whose nodes all kept their reference coordinates has exactly
        the volume ``v_new``, so only the changed cells need the reference
        geometry (bitwise identical).
        """
        cols = cell_columns(cells)
        self.v_ref = v_new.copy()
        ch = cells_touching(self.moved_new, cols)
        self.v_ref[ch] = signed_volumes(self.x_ref, cells[ch], gdim)
        if self.x_before is not None:
            assert self.moved_before is not None
            self.v_before = self.v_ref.copy()
            ch = cells_touching(self.moved_before, cols)
            self.v_before[ch] = signed_volumes(self.x_before, cells[ch], gdim)
        return self.v_ref


def _max_timings(comm: mpi4py.MPI.Comm, timings: dict[str, float]) -> dict[str, float]:
    """Stage -> seconds, the largest over the processes (collective).

    Stages missing on a process count 0 there; the caller's stage order is
    kept, stages known only elsewhere follow in sorted order.
    """
    keys = sorted(timings)
    allkeys = sorted(set().union(*comm.allgather(keys)))
    out = {k: comm.allreduce(float(timings.get(k, 0.0)), op=mpi4py.MPI.MAX) for k in allkeys}
    order = [k for k in timings if k in out]
    order += [k for k in allkeys if k not in order]
    return {k: out[k] for k in order}


@dataclasses.dataclass
class MetricSummary:
    """Global summary of one per-cell measure (reduced over MPI ranks).

    Attributes:
        min, mean, max: over all owned cells of all ranks (NaN if no cells).
        bins: (nb + 1,) fixed histogram bin edges.
        hist: (nb,) int cell counts per bin (values outside are clipped into
            the first / last bin).
    """

    min: float
    mean: float
    max: float
    bins: np.ndarray
    hist: np.ndarray

    @classmethod
    def reduce(cls, comm: mpi4py.MPI.Comm, values: np.ndarray, bins: np.ndarray) -> MetricSummary:
        """Collective: summarise ``values`` (owned cells) over ``comm``."""
        values = np.asarray(values, dtype=np.float64)
        n = comm.allreduce(values.size)
        s = comm.allreduce(float(values.sum()))
        lo = comm.allreduce(float(values.min()) if values.size else math.inf, op=mpi4py.MPI.MIN)
        hi = comm.allreduce(float(values.max()) if values.size else -math.inf, op=mpi4py.MPI.MAX)
        # bin i holds bins[i] <= v < bins[i+1] (last bin closed); outside
        # values are clipped into the first / last bin (as np.histogram of
        # the clipped values, but without its sort)
        # (count of interior edges e with not v < e: as searchsorted(side="right")
        # with the clipping, NaN last; one comparison pass per edge, no search)
        idx: np.ndarray = np.zeros(values.size, dtype=np.uint8 if len(bins) <= 256 else np.intp)
        for e in np.asarray(bins, dtype=np.float64)[1:-1]:
            idx += ~(values < e)
        h = np.bincount(idx, minlength=len(bins) - 1)
        h = comm.allreduce(h.astype(np.int64), op=mpi4py.MPI.SUM)
        if n == 0:
            lo = hi = mean = math.nan
        else:
            mean = s / n
        return cls(float(lo), float(mean), float(hi), np.asarray(bins, dtype=np.float64),
                   np.asarray(h, dtype=np.int64))

    def as_dict(self) -> dict[str, Any]:
        return {"min": self.min, "mean": self.mean, "max": self.max,
                "bins": self.bins.tolist(), "hist": self.hist.tolist()}


@dataclasses.dataclass
class QualityReport:
    """Mesh-quality report of one snap/smooth step (identical on all ranks).

    Attributes:
        n_cells: global number of cells.
        min_angle, max_angle: summaries of the per-cell minimum / maximum
            angle (degrees; triangle angles in 2D, dihedral angles in 3D).
        radius_ratio, mean_ratio: summaries of the normalised ratios
            (1 = equilateral, negative = inverted w.r.t. the reference).
        n_inverted_before: global number of cells inverted (or below the
            relative volume floor) w.r.t. the reference mesh before
            smoothing (boundary nodes moved, interior not yet moved); -1 if
            unknown.
        n_inverted_after: same after smoothing / repair; -1 if unknown.
        n_moved: global number of geometry nodes whose final position differs
            from the reference position.
        max_displacement: max |x_new - x_ref| over all nodes (length unit).
        n_shortfall: number of prescribed (boundary) nodes that could not be
            moved all the way to their target.
        max_shortfall: largest remaining distance to the target among them.
        timings: stage name -> seconds (max over ranks).
        gdim: geometric dimension.
        scope: ``"all"`` (the metrics cover every cell of the mesh) or
            ``"changed"`` (only the cells with a node that moved, i.e. the
            cells snapping and smoothing changed; inversion counts are the
            same either way, as an unchanged cell cannot invert).
        n_cells_mesh: global number of cells of the mesh (``n_cells`` is the
            number of cells the metrics cover).
    """

    n_cells: int
    min_angle: MetricSummary
    max_angle: MetricSummary
    radius_ratio: MetricSummary
    mean_ratio: MetricSummary
    n_inverted_before: int = -1
    n_inverted_after: int = -1
    n_moved: int = 0
    max_displacement: float = 0.0
    n_shortfall: int = 0
    max_shortfall: float = 0.0
    timings: dict[str, float] = dataclasses.field(default_factory=dict)
    gdim: int = 2
    scope: str = "all"
    n_cells_mesh: int = -1

    # -- construction --------------------------------------------------------
    @classmethod
    def from_arrays(cls, comm: mpi4py.MPI.Comm, x_new: np.ndarray, cells: np.ndarray, gdim: int,
                    num_owned_nodes: int | None = None, *,
                    x_ref: np.ndarray | None = None,
                    x_before: np.ndarray | None = None,
                    rel_floor: float = 1e-12,
                    timings: dict[str, float] | None = None,
                    shortfall: np.ndarray | None = None,
                    scope: str = "all") -> QualityReport:
        """Collective: build the report from raw arrays.

        Args:
            comm: MPI communicator (mpi4py).
            x_new: (n, 3) final node coordinates.
            cells: (nc_owned, gdim + 1) node indices of the cells OWNED by
                this rank (ghost cells must be excluded to avoid double
                counting).
            gdim: 2 or 3.
            num_owned_nodes: the first ``num_owned_nodes`` rows of ``x`` are
                owned by this rank (default: all rows).
            x_ref: (n, 3) reference (straight) coordinates; enables the
                inversion counts, orientation-aware ratios and displacement
                statistics.
            x_before: (n, 3) coordinates before smoothing (boundary nodes
                moved only); enables ``n_inverted_before``.
            rel_floor: relative volume floor of :func:`inverted_cells`.
            timings: stage -> seconds on this rank (max over ranks is kept).
            shortfall: (k,) remaining distances of the prescribed nodes OWNED
                by this rank that did not reach their target (only entries
                > 0 are counted).
            scope: ``"all"``: metrics over all ``cells``; ``"changed"``
                (needs ``x_ref``): only over the cells with a node whose
                coordinates in ``x_new`` or ``x_before`` differ from
                ``x_ref`` (O(changed cells) geometry instead of O(mesh)).
        """
        if scope not in ("all", "changed"):
            raise ValueError(f"scope must be 'all' or 'changed', not {scope!r}")
        if scope == "changed" and x_ref is None:
            raise ValueError("scope='changed' needs x_ref")
        x_new = np.asarray(x_new, dtype=np.float64)
        cells = np.asarray(cells)
        n_cells_mesh = comm.allreduce(int(cells.shape[0]))
        ref = None
        if x_ref is not None:
            ref = _Reference(x_new, x_ref, x_before)
            if scope == "changed":
                cells = cells[cells_touching(ref.changed, cell_columns(cells))]
        q = quality_stats(x_new, cells, gdim)
        if ref is not None:
            _orient(q, ref.volumes(cells, q["volume"], gdim))
        rep = cls(
            n_cells=comm.allreduce(int(cells.shape[0])),
            scope=scope,
            n_cells_mesh=n_cells_mesh,
            min_angle=MetricSummary.reduce(comm, q["min_angle"], ANGLE_BINS),
            max_angle=MetricSummary.reduce(comm, q["max_angle"], ANGLE_BINS),
            radius_ratio=MetricSummary.reduce(comm, q["radius_ratio"], RATIO_BINS),
            mean_ratio=MetricSummary.reduce(comm, q["mean_ratio"], RATIO_BINS),
            gdim=gdim,
        )
        if ref is not None:
            nown = x_new.shape[0] if num_owned_nodes is None else int(num_owned_nodes)
            rep._count_inversions(comm, ref, q["volume"], rel_floor)
            rep._displacements(comm, x_new[:nown] - ref.x_ref[:nown])
        if shortfall is not None:
            rep._shortfalls(comm, np.asarray(shortfall, dtype=np.float64))
        if timings:
            rep.timings = _max_timings(comm, timings)
        return rep

    def _count_inversions(self, comm: mpi4py.MPI.Comm, ref: _Reference, v_new: np.ndarray, rel_floor: float) -> None:
        """Set ``n_inverted_after`` (and ``n_inverted_before`` with ``x_before``) (collective)."""
        assert ref.v_ref is not None  # set by ref.volumes
        self.n_inverted_after = comm.allreduce(
            int(np.count_nonzero(inverted_mask(v_new, ref.v_ref, rel_floor))))
        if ref.v_before is not None:
            self.n_inverted_before = comm.allreduce(
                int(np.count_nonzero(inverted_mask(ref.v_before, ref.v_ref, rel_floor))))

    def _displacements(self, comm: mpi4py.MPI.Comm, disp: np.ndarray) -> None:
        """Set ``n_moved`` and ``max_displacement`` from the owned nodes' ``disp (k, 3)`` (collective)."""
        d = np.linalg.norm(disp, axis=1)
        self.n_moved = comm.allreduce(int(np.count_nonzero(d > 0.0)))
        self.max_displacement = comm.allreduce(float(d.max()) if d.size else 0.0,
                                               op=mpi4py.MPI.MAX)

    def _shortfalls(self, comm: mpi4py.MPI.Comm, shortfall: np.ndarray) -> None:
        """Set ``n_shortfall`` and ``max_shortfall`` from the owned ``shortfall (k,)`` (collective)."""
        sf = shortfall[shortfall > 0.0]
        self.n_shortfall = comm.allreduce(int(sf.size))
        self.max_shortfall = comm.allreduce(float(sf.max()) if sf.size else 0.0,
                                            op=mpi4py.MPI.MAX)

    @classmethod
    def from_mesh(cls, mesh: dolfinx.mesh.Mesh, x_new: np.ndarray | None = None, **kwargs) -> QualityReport:
        """Collective: report for a DOLFINx P1 simplex mesh.

        Args:
            mesh: ``dolfinx.mesh.Mesh`` (triangles or tetrahedra, P1 geometry).
            x_new: (n, 3) coordinates to assess (default ``mesh.geometry.x``).
            **kwargs: ``x_ref``, ``x_before``, ``rel_floor``, ``timings``,
                ``shortfall`` as in :meth:`from_arrays`.
        """
        tdim = mesh.topology.dim
        n_own_cells = mesh.topology.index_map(tdim).size_local
        cells = mesh.geometry.dofmaps[0][:n_own_cells]
        x = mesh.geometry.x if x_new is None else x_new
        return cls.from_arrays(mesh.comm, x, cells, mesh.geometry.dim,
                               mesh.geometry.index_map().size_local, **kwargs)

    # -- output ----------------------------------------------------------------
    def as_dict(self) -> dict[str, Any]:
        """Plain (JSON-serialisable) dict of all fields."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, MetricSummary):
                v = v.as_dict()
            elif isinstance(v, dict):
                v = dict(v)
            out[f.name] = v
        return out

    def __str__(self) -> str:
        ang = "dihedral angle" if self.gdim == 3 else "angle"
        if self.scope == "changed":
            lines = [f"mesh quality report ({self.n_cells} changed cells of {self.n_cells_mesh}, "
                     f"gdim={self.gdim})"]
        else:
            lines = [f"mesh quality report ({self.n_cells} cells, gdim={self.gdim})"]
        w = 24
        lines.append(f"  {'measure':<{w}} {'min':>10} {'mean':>10} {'max':>10}")
        rows = [(f"min {ang} [deg]", self.min_angle),
                (f"max {ang} [deg]", self.max_angle),
                ("radius ratio", self.radius_ratio),
                ("mean ratio", self.mean_ratio)]
        for name, m in rows:
            lines.append(f"  {name:<{w}} {m.min:>10.4g} {m.mean:>10.4g} {m.max:>10.4g}")
        lines.append("  histograms (cell counts per bin)")
        for name, m in rows:
            b = m.bins
            labels = [f"{b[i]:g}-{b[i + 1]:g}" for i in range(len(b) - 1)]
            cw = max(max(len(s) for s in labels), max(len(str(c)) for c in m.hist)) + 1
            lines.append(f"    {name:<{w - 2}} " + "".join(f"{s:>{cw}}" for s in labels))
            lines.append(f"    {'':<{w - 2}} " + "".join(f"{c:>{cw}d}" for c in m.hist))

        def kv(k: str, v: object) -> None:
            lines.append(f"  {k:<{w}} {v}")

        kv("inverted before smooth", self.n_inverted_before if self.n_inverted_before >= 0 else "n/a")
        kv("inverted after smooth", self.n_inverted_after if self.n_inverted_after >= 0 else "n/a")
        kv("vertices moved", self.n_moved)
        kv("max displacement", f"{self.max_displacement:.6g}")
        kv("not fully moved", self.n_shortfall)
        kv("max shortfall", f"{self.max_shortfall:.6g}")
        if self.timings:
            lines.append("  timings [s]")
            for k, v in self.timings.items():
                lines.append(f"    {k:<{w - 2}} {v:>10.4f}")
            if "total" not in self.timings:
                lines.append(f"    {'sum':<{w - 2}} {sum(self.timings.values()):>10.4f}")
        return "\n".join(lines)
