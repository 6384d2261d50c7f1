"""CAD mode: snap boundary vertices onto NURBS curves (2D) or surfaces (3D).

:class:`CadGeometry` is the snapping geometry of Kadir (2010), chapter 2:

* :meth:`CadGeometry.attach` is the initialisation of the coarse mesh
  (Kadir 2.3.1): every boundary vertex is located on the CAD geometry by a
  global search (:class:`nagata_snap.cad.projection.GlobalSearcher`) and each
  boundary facet is assigned ONE entity (curve or surface patch) on which all
  its vertices lie (the assumption of Kadir 2.3.4).  The per-vertex
  parameters are stored per facet (Kadir 2.3.2: the ``(n, u)`` / ``(n, u, v)``
  tuples) in :class:`nagata_snap.records.Records`.
* :meth:`CadGeometry.place` is the snapping after a refinement (Kadir 2.2,
  Algorithm 1, with the neighbour-information seeds of 2.3.3): each facet
  vertex is projected by Newton (Kadir App. B, eqs. B.1/B.2) onto its facet's
  entity, seeded with the parameters carried by the records (for a new vertex,
  the parametric midpoint of its parent edge).

Trimmed faces (IGES 144/142, Kadir 2.3): with ``trim_loops``/``trim_holes``
(:meth:`CadGeometry.from_iges` passes the file's) a projection counts only if
its ``(u, v)`` lies inside the face's outer loop and outside its holes
(:class:`TrimLoops`, within a small parametric band so that points on a face
boundary shared with another face count on both).  The global searches of
:meth:`~CadGeometry.attach`, :meth:`~CadGeometry.closest_point` and of the
:meth:`~CadGeometry.place` fallbacks ignore results on a surface's extension
beyond its face, and a seeded Newton result that leaves its facet's face
falls back to the neighbouring faces.  A vertex shared by facets of several
entities (a vertex on a CAD edge) is put onto all of them (Gauss-Newton onto
the intersection of the surfaces), so that, e.g., a new vertex between two
vertices on the rim of a hole lands on the rim, not on the plane inside the
hole.

Parameters in closed (periodic) directions are kept *unwrapped per facet*: the
vertices of one facet never differ by a jump of a period, so parametric
midpoints are correct across seams.  Evaluation wraps them.

Example (2D, a NURBS circle and a polygon of its points)::

    >>> import numpy as np
    >>> from nagata_snap.cad.nurbs import NurbsCurve
    >>> from nagata_snap.cad import CadGeometry
    >>> s = np.sqrt(0.5)
    >>> P = [[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1], [0, -1], [1, -1], [1, 0]]
    >>> circle = NurbsCurve(2, [0, 0, 0, .25, .25, .5, .5, .75, .75, 1, 1, 1], P,
    ...                     [1, s, 1, s, 1, s, 1, s, 1])
    >>> geo = CadGeometry([circle])
    >>> t = np.linspace(0, 2 * np.pi, 9)[:-1]
    >>> x = np.c_[np.cos(t), np.sin(t), 0 * t]
    >>> facets = np.stack([x, np.roll(x, -1, axis=0)], axis=1)   # (8, 2, 3)
    >>> rec = geo.attach(facets)
    >>> mid = facets.mean(axis=1)                                 # straight midpoints
    >>> straight = np.stack([facets[:, 0], mid], axis=1)          # first halves
    >>> rec.params = np.stack([rec.params[:, 0], rec.params.mean(axis=1)], axis=1)
    >>> pts, rec2, report = geo.place(rec, straight)
    >>> bool(np.allclose(np.linalg.norm(pts, axis=2), 1.0, atol=1e-13, rtol=0))
    True

With DOLFINx, ``facet_points`` are the coordinates of the tagged boundary
facets' vertices (``mesh.geometry.x[...]``); the lead's ``Snapper`` hook calls
``attach`` once on the coarse mesh and ``place`` after every refinement.
"""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np
import numpy.typing as npt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .iges import points_in_polygon
from .nurbs import NurbsCurve, NurbsSurface
from .projection import GlobalSearcher, evaluate_params, normalize_params
from ..records import Records

__all__ = ["CadError", "CadGeometry", "TrimLoops"]

#: two facet vertices closer than this (relative to the model size) are one vertex
MERGE_RTOL = 1e-10
#: a parameter direction is degenerate at a point (pole) if ``|dS/dp|`` is below
#: this fraction of the entity size (per unit parameter)
DEGENERATE_RTOL = 1e-9
#: default trimming tolerance: a projection whose ``(u, v)`` lies outside its face
#: (outside the outer loop or inside a hole) by more than this fraction of the
#: loop's parametric size (beyond the loop's sampling band) is rejected
TRIM_RTOL = 1e-6
#: turning angle (radians) above which a trimming-polygon vertex is a corner of the
#: loop, not a sample of a smooth trimming curve
CORNER_ANGLE = 0.35
#: an edge vertex (on facets of several entities) counts as on all of them within
#: this fraction of the model size
EDGE_RTOL = 1e-14
#: alternating-projection sweeps that bring an edge vertex onto all its entities
EDGE_SWEEPS = 8


class CadError(RuntimeError):
    """The mesh boundary does not match the CAD geometry (or no geometry found)."""


def _facets(a: npt.ArrayLike, what: str) -> np.ndarray:
    x = np.asarray(a, dtype=float)
    if x.ndim != 3 or x.shape[2] not in (2, 3) or x.shape[1] < 1:
        raise ValueError(f"{what} must have shape (nf, nfv, 3), got {x.shape}")
    if x.shape[2] == 2:
        x = np.concatenate([x, np.zeros(x.shape[:2] + (1,))], axis=2)
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{what} contains NaN or infinite coordinates")
    return x


def _edge_length(x: np.ndarray) -> np.ndarray:
    """Largest edge (vertex-pair distance) of each facet ``(nf, nfv, 3)`` -> ``(nf,)``."""
    nfv = x.shape[1]
    h = np.zeros(x.shape[0])
    for i in range(nfv):  # loop over facet vertices (2 or 3)
        for j in range(i + 1, nfv):
            np.maximum(h, np.linalg.norm(x[:, i] - x[:, j], axis=1), out=h)
    return h


def _unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distinct rows of ``a (n, k)`` (float): ``(first (m,), inverse (n,), rows (m, k))``.

    As ``np.unique(a, axis=0, return_index=True, return_inverse=True)`` (rows
    compared by value: ``-0.0 == 0.0``; a row with NaN is its own group), but
    with one ``np.lexsort`` of the columns instead of a sort of the rows as
    opaque byte strings, which is ~10x faster.
    """
    a = np.ascontiguousarray(a)
    n = a.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp), a[:0]
    order = np.lexsort(a.T[::-1])  # stable: equal rows keep their input order
    srt = a[order]
    new = np.ones(n, dtype=bool)
    new[1:] = np.any(srt[1:] != srt[:-1], axis=1)
    inverse = np.empty(n, dtype=np.intp)
    inverse[order] = np.cumsum(new) - 1
    return order[new], inverse, srt[new]


def _groups(points: np.ndarray, radius: float, nodes: np.ndarray | None = None) -> np.ndarray:
    """Vertex id per point: equal ``nodes`` ids, else points closer than ``radius``."""
    if nodes is not None:
        return np.unique(np.asarray(nodes).reshape(-1), return_inverse=True)[1].reshape(-1)
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    _, inv, uniq = _unique_rows(points)
    pairs = cKDTree(uniq).query_pairs(radius, output_type="ndarray")
    if len(pairs):
        m = len(uniq)
        g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
        _, lab = connected_components(g, directed=False)
        return lab[inv]
    return inv


class TrimLoops:
    """Trimmed faces in parameter space: is a surface point ``(u, v)`` on its face?

    IGES 144/142 faces (Kadir 2010, sec. 2.3): per surface an outer loop and
    holes, polygons in the surface's ``(u, v)`` NURBS parameters through points
    of the true trimming curves (see :class:`nagata_snap.cad.iges.IgesModel`).

    Between two polygon vertices the true curve deviates from the chord by up
    to its sagitta, estimated as ``L * phi / 8`` (``L`` the chord, ``phi`` the
    larger turning angle at its ends; vertices turning by more than
    :data:`CORNER_ANGLE` are corners of the loop, which add nothing).  A point
    within twice that, plus ``rtol`` times the loop's parametric size, of a
    segment counts as on the loop, so points on a trimming curve (a face
    boundary shared with another face) are accepted by both faces.

    Args:
        entities: the surfaces.
        outer: per surface the outer loop ``(k, 2)`` or ``None`` (untrimmed).
        holes: per surface a list of inner loops ``(k, 2)`` (or ``None``).
        rtol: parametric tolerance, relative to each loop's size.
    """

    def __init__(self, entities, outer=None, holes=None, rtol: float = TRIM_RTOL):
        n = len(entities)
        for name, arr in (("trim_loops", outer), ("trim_holes", holes)):
            if arr is not None and len(arr) != n:
                raise ValueError(f"{name} has {len(arr)} entries for {n} entities")
        self.rtol = float(rtol)
        self._loops: list[list[tuple]] = []
        for e in range(n):  # loop over entities
            loops = []
            o = None if outer is None else outer[e]
            hs = [] if holes is None or holes[e] is None else list(holes[e])
            for k, (poly, hole) in enumerate([(o, False)] + [(h, True) for h in hs]):
                if poly is None:
                    continue
                P = np.asarray(poly, dtype=float)
                if P.ndim != 2 or P.shape[1] != 2 or not np.all(np.isfinite(P)):
                    raise ValueError(f"entity {e}: trimming loop {k} must be a finite (k, 2) polygon, got {P.shape}")
                if len(P) > 1 and np.array_equal(P[0], P[-1]):
                    P = P[:-1]
                if len(P) < 3:
                    raise ValueError(f"entity {e}: trimming loop {k} has fewer than 3 vertices")
                loops.append(self._prepare(P, hole))
            self._loops.append(loops)
        self.trimmed = np.array([bool(lp) for lp in self._loops])
        self._period = np.full((n, 2), np.nan)
        for e, ent in enumerate(entities):
            if ent.param_dim == 2:
                for a, closed in enumerate(ent.closed):
                    if closed:
                        self._period[e, a] = np.diff(ent.bounds[a])[0]
        self.entities = list(entities)

    def _prepare(self, P: np.ndarray, hole: bool) -> tuple:
        seg = np.roll(P, -1, axis=0) - P
        L = np.linalg.norm(seg, axis=1)
        prev = np.roll(seg, 1, axis=0)
        Lp = np.roll(L, 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            c = np.einsum("ij,ij->i", prev, seg) / (Lp * L)
        phi = np.arccos(np.clip(np.nan_to_num(c, nan=1.0), -1.0, 1.0))  # turning angle at vertex i
        phi[phi > CORNER_ANGLE] = 0.0
        band = 2.0 * L * np.maximum(phi, np.roll(phi, -1)) / 8.0
        size = float(np.linalg.norm(P.max(axis=0) - P.min(axis=0)))
        band += self.rtol * size
        return P, seg, np.maximum(L * L, 1e-300), band, hole

    @staticmethod
    def _loop_excess(loop: tuple, q: np.ndarray) -> np.ndarray:
        """Parametric distance outside the face beyond the band, ``(m,)``.

        ``<= 0`` accepted; ``-inf`` on the face side of the polygon (no
        distance computed there).
        """
        P, seg, L2, band, hole = loop
        inside = points_in_polygon(P, q)
        out_idx = np.flatnonzero(inside if hole else ~inside)
        ex = np.full(len(q), -np.inf)
        step = max(1, 400_000 // len(P))
        for i in range(0, out_idx.size, step):  # chunks bound the (c, k) work arrays
            sel = out_idx[i:i + step]
            qq = q[sel, None, :] - P[None]  # (c, k, 2)
            t = np.clip(np.einsum("ckj,kj->ck", qq, seg) / L2, 0.0, 1.0)
            r = qq - t[:, :, None] * seg[None]
            d = np.sqrt(np.einsum("ckj,ckj->ck", r, r))
            ex[sel] = (d - band[None]).min(axis=1)
        return ex

    def excess(self, ent: npt.ArrayLike, params: npt.ArrayLike) -> np.ndarray:
        """``(n,)`` parametric excess of ``params (n, 2)`` outside face ``ent (n,)``.

        ``<= 0`` means on the face (``-inf`` well inside it or for untrimmed
        surfaces); a positive value is the parametric distance to the nearest
        loop beyond its tolerance band.  Closed directions are tested at the
        wrapped parameter and, where that is outside, one period either side.
        """
        ent = np.asarray(ent, dtype=np.int64).reshape(-1)
        params = np.asarray(params, dtype=float).reshape(len(ent), -1)
        out = np.full(len(ent), -np.inf)
        if len(ent) == 0 or not self.trimmed.any():
            return out
        for e in np.unique(ent[self.trimmed[ent]]):  # loop over trimmed entities
            sel = np.flatnonzero(ent == e)
            q0 = normalize_params(self.entities[e], params[sel])
            shifts = [np.zeros(2)]
            for a in range(2):
                if not np.isnan(self._period[e, a]):
                    d = np.zeros(2)
                    d[a] = self._period[e, a]
                    shifts = [s + k * d for s in shifts for k in (0.0, -1.0, 1.0)]
            best = np.full(len(sel), np.inf)
            todo = np.arange(len(sel))
            for sh in shifts:  # at most 9 (both directions closed); the first is 0
                q = q0[todo] + sh
                ex = np.full(todo.size, -np.inf)
                for loop in self._loops[e]:  # outer loop and holes
                    np.maximum(ex, self._loop_excess(loop, q), out=ex)
                best[todo] = np.minimum(best[todo], ex)
                todo = todo[ex > 0]
                if todo.size == 0:
                    break
            out[sel] = best
        return out

    def inside(self, ent: npt.ArrayLike, params: npt.ArrayLike) -> np.ndarray:
        """``(n,)`` bool: ``params`` lies on face ``ent`` (within the tolerance band)."""
        return self.excess(ent, params) <= 0.0

    def loop_points(self, e: int) -> np.ndarray | None:
        """All loop vertices of surface ``e`` ``(k, 2)``, or ``None`` if untrimmed."""
        if not self._loops[e]:
            return None
        return np.concatenate([lp[0] for lp in self._loops[e]])


class CadGeometry:
    """Snapping geometry from NURBS curves (2D meshes) or surfaces (3D meshes).

    Args:
        entities: the CAD entities, all :class:`~nagata_snap.cad.nurbs.NurbsCurve`
            (2D: boundary segments are snapped to curves) or all
            :class:`~nagata_snap.cad.nurbs.NurbsSurface` (3D: triangles to surfaces).
        trim_loops: surfaces only: per entity the outer trimming loop, a
            ``(k, 2)`` polygon in its ``(u, v)`` parameters, or ``None`` (the
            whole surface is the face); e.g. ``IgesModel.trim_loops``.
        trim_holes: surfaces only: per entity a list of inner loops
            (``IgesModel.trim_holes``).
        tol_factor: :meth:`attach` accepts a facet if all its vertices are
            within ``tol_factor * h`` of one entity, ``h`` the facet's longest
            edge (dimensionless).
        k_seeds: nearest grid samples used as Newton seeds in global searches.
        max_iter: Newton iterations per projection in :meth:`place`.
        per_span: samples per knot span and direction of the search grid.
        trim_rtol: parametric tolerance of the trimming test, relative to each
            loop's parametric size (see :class:`TrimLoops`).

    With trimming loops a projection counts only if its ``(u, v)`` lies on the
    face (:class:`TrimLoops`): the global searches of :meth:`attach` and of the
    :meth:`place` fallbacks ignore results on a surface's extension beyond its
    face, and a seeded Newton result that leaves its facet's face falls back
    to the neighbouring faces.  The search grid keeps only samples on the face
    (plus the loop vertices).

    Raises:
        ValueError: empty or mixed entity list, trimming loops for curves or of
            the wrong count.
    """

    def __init__(
        self,
        entities: Sequence[NurbsCurve] | Sequence[NurbsSurface],
        trim_loops: Sequence[np.ndarray | None] | None = None,
        trim_holes: Sequence[Sequence[np.ndarray] | None] | None = None,
        *,
        tol_factor: float = 1e-2,
        k_seeds: int = 6,
        max_iter: int = 20,
        per_span: int | None = None,
        trim_rtol: float = TRIM_RTOL,
    ):
        entities = list(entities)
        if not entities:
            raise ValueError("CadGeometry needs at least one NURBS curve or surface")
        kinds = {type(e) for e in entities}
        if not (kinds <= {NurbsCurve} or kinds <= {NurbsSurface}):
            raise ValueError(
                f"entities must be all NurbsCurve or all NurbsSurface, got {sorted(k.__name__ for k in kinds)}"
            )
        self.entities = entities
        self.param_dim = entities[0].param_dim
        self.tol_factor = float(tol_factor)
        self.max_iter = int(max_iter)
        for name, arr in (("trim_loops", trim_loops), ("trim_holes", trim_holes)):
            if arr is not None and len(arr) != len(entities):
                raise ValueError(f"{name} has {len(arr)} entries for {len(entities)} entities")
        has_trim = any(t is not None for t in (trim_loops or [])) or any(h for h in (trim_holes or []))
        if has_trim and self.param_dim != 2:
            raise ValueError("trimming loops apply to surfaces only")
        self.trims: TrimLoops | None = (
            TrimLoops(entities, trim_loops, trim_holes, trim_rtol) if has_trim else None
        )
        if self.trims is not None:
            self.searcher = GlobalSearcher(
                entities, per_span=per_span, k_seeds=k_seeds,
                sample_filter=lambda e, P: self.trims.inside(np.full(len(P), e), P),
                extra_samples=[self.trims.loop_points(e) for e in range(len(entities))],
            )
        else:
            self.searcher = GlobalSearcher(entities, per_span=per_span, k_seeds=k_seeds)
        self.size = self.searcher.size
        d = self.param_dim
        self._period = np.full((len(entities), d), np.nan)
        for i, e in enumerate(entities):
            for a, closed in enumerate(e.closed):
                if closed:
                    lo, hi = e.bounds[a]
                    self._period[i, a] = hi - lo

    @property
    def _accept(self):
        """``f(ent, params) -> bool`` (on the trimmed face), or ``None`` without trims."""
        return None if self.trims is None else self.trims.inside

    def inside(self, ent: npt.ArrayLike, params: npt.ArrayLike) -> np.ndarray:
        """``(n,)`` bool: ``params (n, d)`` of entity ``ent (n,)`` lie on its (trimmed) face."""
        ent = np.asarray(ent, dtype=np.int64).reshape(-1)
        if self.trims is None:
            return np.ones(len(ent), dtype=bool)
        return self.trims.inside(ent, params)

    @classmethod
    def from_iges(
        cls, path: str | os.PathLike, *, dim: int | None = None, **kwargs
    ) -> "CadGeometry":
        """Geometry from the NURBS entities of an IGES file.

        Uses :func:`nagata_snap.cad.iges.read_iges`, whose result has ``.curves``
        and ``.surfaces`` (as NURBS) and, per surface, ``.trim_loops`` and
        ``.trim_holes`` (144/142 trimming loops in parameter space), which are
        passed on for the surfaces.

        Args:
            path: IGES file.
            dim: mesh dimension: 2 uses the curves, 3 the surfaces; ``None``
                uses the surfaces if there are any, else the curves.
            **kwargs: passed to :class:`CadGeometry`.

        Raises:
            CadError: the file holds no entity of the kind needed.
        """
        from .iges import read_iges

        model = read_iges(path)
        curves = list(getattr(model, "curves", []) or [])
        surfaces = list(getattr(model, "surfaces", []) or [])
        if dim is None:
            ents, kind = (surfaces, "surfaces") if surfaces else (curves, "curves")
        elif dim == 2:
            ents, kind = curves, "curves"
        elif dim == 3:
            ents, kind = surfaces, "surfaces"
        else:
            raise ValueError(f"dim must be 2, 3 or None, got {dim!r}")
        if not ents:
            raise CadError(
                f"{os.fspath(path)}: no NURBS {kind} found (the file has {len(curves)} "
                f"curves and {len(surfaces)} surfaces)"
            )
        if kind == "surfaces":
            loops = list(getattr(model, "trim_loops", []) or [])
            holes = list(getattr(model, "trim_holes", []) or [])
            kwargs.setdefault("trim_loops", loops if len(loops) == len(ents) else None)
            kwargs.setdefault("trim_holes", holes if len(holes) == len(ents) else None)
        return cls(ents, **kwargs)

    # ------------------------------------------------------------------
    @property
    def num_entities(self) -> int:
        """Number of CAD entities."""
        return len(self.entities)

    def evaluate(self, root: npt.ArrayLike, params: np.ndarray) -> np.ndarray:
        """Points of records: entity ``root (nf,)`` at ``params (nf, nfv, d)`` -> ``(nf, nfv, 3)``.

        Parameters are wrapped/clamped into each entity's domain.
        """
        root = np.asarray(root, dtype=np.int64).reshape(-1)
        params = np.asarray(params, dtype=float)
        nf, nfv, d = params.shape
        out = np.empty((nf, nfv, 3))
        for e in np.unique(root):  # loop over entities
            sel = root == e
            p = normalize_params(self.entities[e], params[sel].reshape(-1, d))
            out[sel] = evaluate_params(self.entities[e], p, 0).reshape(-1, nfv, 3)
        return out

    def closest_point(self, points: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest point of each point on the (trimmed) faces: global search.

        Newton from the ``k_seeds`` nearest grid samples (samples on the faces
        only); a result on a surface's extension beyond its face's trimming
        loops does not count, so a point is attributed to the face that really
        contains its closest point, not to a larger surface's extension.

        Returns:
            ``(entity (n,) int64, params (n, d), distance (n,))``; entity ``-1``
            and distance ``inf`` where no seed converged onto a face (e.g. the
            closest point is a face corner that is a stationary point of no
            surface).
        """
        X = np.asarray(points, dtype=float)
        res = self.searcher.search(X, accept=self._accept)
        ent, par, dist = res[:3]
        if self.trims is not None:
            ok = res[3]
            ent = np.where(ok, ent, -1)
            dist = np.where(ok, dist, np.inf)
        return ent.astype(np.int64), par, dist

    # ------------------------------------------------------------------
    def _unwrap(self, root: np.ndarray, params: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """Shift ``params (n, d)`` by whole periods to be nearest to ``ref (n, d)``."""
        per = self._period[root]  # (n, d), nan where open
        use = ~np.isnan(per) & np.isfinite(ref)
        shift = np.round((np.where(use, ref, 0.0) - params) / np.where(use, per, 1.0))
        return params + np.where(use, shift * per, 0.0)

    def _degenerate(self, root: np.ndarray, params: np.ndarray) -> np.ndarray:
        """``(n, d)`` bool: tangent ``dS/dp_a`` vanishes (e.g. the poles of a sphere)."""
        n, d = params.shape
        out = np.zeros((n, d), dtype=bool)
        for e in np.unique(root):  # loop over entities
            sel = np.flatnonzero(root == e)
            ent = self.entities[e]
            p = normalize_params(ent, params[sel])
            _, T = evaluate_params(ent, p, 1)
            lengths = np.diff(ent.bounds, axis=1)[:, 0]  # (d,)
            thr = DEGENERATE_RTOL * ent.bbox_size / lengths
            out[sel] = np.linalg.norm(T, axis=2) <= thr[None, :]
        return out

    def _contiguous(self, root: np.ndarray, params: np.ndarray) -> np.ndarray:
        """Unwrap each facet's params across seams; fill degenerate (pole) parameters.

        ``params (nf, nfv, d)``: in each closed direction every vertex is
        shifted by whole periods towards the facet's first non-degenerate
        vertex; a parameter that is arbitrary at its vertex (a pole, where
        ``dS/dp = 0``) is replaced by the mean of the facet's other vertices,
        so that parametric midpoints of edges at the pole stay sensible.
        """
        nf, nfv, d = params.shape
        if nf == 0:
            return params
        flat_root = np.repeat(root, nfv)
        degen = self._degenerate(flat_root, params.reshape(-1, d)).reshape(nf, nfv, d)
        out = params.copy()
        rows = np.arange(nf)
        for a in range(d):  # loop over parameter directions
            good = ~degen[:, :, a]
            refslot = np.argmax(good, axis=1)  # first non-degenerate slot (0 if none)
            ref = out[rows, refslot, a]
            per = self._period[root, a]
            closed = ~np.isnan(per)
            if closed.any():
                pc = per[closed][:, None]
                col = out[closed, :, a]
                out[closed, :, a] = col + pc * np.round((ref[closed][:, None] - col) / pc)
            cnt = good.sum(axis=1)
            fix = degen[:, :, a] & (cnt > 0)[:, None]
            if fix.any():
                mean = np.where(good, out[:, :, a], 0.0).sum(axis=1) / np.maximum(cnt, 1)
                out[:, :, a] = np.where(fix, mean[:, None], out[:, :, a])
        return out

    # ------------------------------------------------------------------
    def attach(self, facet_points: npt.ArrayLike, nodes: npt.ArrayLike | None = None) -> Records:
        """Records of the coarse mesh's boundary facets (global search, Kadir 2.3.1).

        Args:
            facet_points: ``(nf, nfv, 3)`` vertex coordinates of the boundary
                facets to snap (2D: ``nfv = 2`` segments in the z = 0 plane,
                matched to curves; 3D: ``nfv = 3`` triangles, matched to surfaces).
            nodes: optional ``(nf, nfv)`` global vertex ids (vertex identity);
                by default vertices are identified by their coordinates.

        Returns:
            :class:`Records`: ``root (nf,)`` int64 entity per facet, the one
            minimising the largest vertex distance; ``params (nf, nfv, d)``
            of its vertices on it, unwrapped per facet in closed directions.

        Raises:
            CadError: a facet has a vertex farther than ``tol_factor * h`` (``h``
                its longest edge) from every entity; the message names the
                facet and the distance.
        """
        fp = _facets(facet_points, "facet_points")
        nf, nfv, _ = fp.shape
        d = self.param_dim
        ne = self.num_entities
        if nfv - 1 != d:
            have = "curves" if d == 1 else "surfaces"
            need = "curves (2D mesh, segment facets)" if nfv == 2 else "surfaces (3D mesh, triangle facets)"
            raise CadError(
                f"facets with {nfv} vertices need NURBS {need}; this CadGeometry has {have} "
                "(CadGeometry.from_iges(path, dim=...) picks the kind)"
            )
        if nf == 0:
            return Records(np.zeros(0, dtype=np.int64), np.zeros((0, nfv, d)))
        flat = fp.reshape(-1, 3)
        gid = _groups(flat, MERGE_RTOL * self.size, nodes)
        nv = int(gid.max()) + 1
        rep = np.unique(gid, return_index=True)[1]  # first slot of each vertex
        V = flat[rep]
        h = _edge_length(fp)
        tol = self.tol_factor * h  # (nf,)

        # (vertex, entity) table: best Newton result from the KD-tree seeds
        pt, ent, par, _, dist, _ = self.searcher.search_all(V)
        # best entity per vertex ignoring trims: a candidate of last resort
        any_best = ent[_best_rows(pt, dist, np.ones(len(pt), dtype=bool), nv)]
        if self.trims is not None:
            # results on a surface's extension beyond its face do not count
            ok = self.trims.inside(ent, par)
            lost = np.setdiff1d(np.arange(nv), pt[ok])
            pt, ent, par, dist = pt[ok], ent[ok], par[ok], dist[ok]
            if lost.size:  # every seed of these vertices left its face: more seeds
                p2, e2, q2, _, d2, _ = self.searcher.search_all(V[lost], 4 * self.searcher.k_seeds)
                ok2 = self.trims.inside(e2, q2)
                pt = np.concatenate([pt, lost[p2[ok2]]])
                ent = np.concatenate([ent, e2[ok2]])
                par = np.concatenate([par, q2[ok2]])
                dist = np.concatenate([dist, d2[ok2]])
        keys, par_t, dist_t = self._reduce(pt * ne + ent, par, dist)  # sorted by key
        # best entity per vertex (smallest distance)
        rows = _best_rows(keys // ne, dist_t, np.ones(len(keys), dtype=bool), nv)
        best_ent = np.where(rows >= 0, keys[np.maximum(rows, 0)] % ne if len(keys) else any_best, any_best)

        # candidate (facet, entity) pairs: entities within tolerance of any vertex, and
        # every vertex's best entity
        slot_v = gid.reshape(nf, nfv)
        vstart = np.searchsorted(keys, np.arange(nv) * ne)
        vend = np.searchsorted(keys, (np.arange(nv) + 1) * ne)
        cnt = (vend - vstart)[slot_v.reshape(-1)]
        rowsel = np.repeat(vstart[slot_v.reshape(-1)], cnt) + _ramp(cnt)
        fac = np.repeat(np.repeat(np.arange(nf), nfv), cnt)
        near = dist_t[rowsel] <= tol[fac]
        cf = np.concatenate([fac[near], np.repeat(np.arange(nf), nfv)])
        ce = np.concatenate([keys[rowsel][near] % ne, best_ent[slot_v.reshape(-1)]])
        pair = np.unique(cf * ne + ce)
        cf, ce = pair // ne, pair % ne

        # distance of every vertex of every candidate facet to the candidate entity
        need_v = slot_v[cf].reshape(-1)
        need_e = np.repeat(ce, nfv)
        need = need_v * ne + need_e
        pos = np.searchsorted(keys, need)
        found = (pos < len(keys)) & (keys[np.minimum(pos, len(keys) - 1)] == need)
        if not found.all():
            miss = np.unique(need[~found])
            res = self.searcher.search_on(V[miss // ne], miss % ne, accept=self._accept)
            mp, md = res[0], res[2]
            if self.trims is not None:  # no projection on the trimmed face
                md = np.where(res[3], md, np.inf)
            keys, par_t, dist_t = self._reduce(
                np.concatenate([keys, miss]), np.concatenate([par_t, mp]), np.concatenate([dist_t, md])
            )
            pos = np.searchsorted(keys, need)
        dmax = dist_t[pos].reshape(-1, nfv).max(axis=1)
        # choose per facet: smallest max distance, ties to the lowest entity index
        order = np.lexsort((ce, dmax, cf))
        first = np.searchsorted(cf[order], np.arange(nf))
        choice = order[first]
        root = ce[choice].astype(np.int64)
        score = dmax[choice]
        bad = np.flatnonzero(~(score <= tol))
        if bad.size:
            worst = bad[np.argmax(score[bad] / np.maximum(h[bad], 1e-300))]
            what = (
                f"is {score[worst]:.3e} from the nearest entity ({root[worst]}), more than the tolerance "
                f"{tol[worst]:.3e} = tol_factor {self.tol_factor:g} x facet size {h[worst]:.3e}"
                if np.isfinite(score[worst])
                else "has no projection inside the trimming loops of any single face"
            )
            raise CadError(
                f"{bad.size} of {nf} boundary facets do not lie on the CAD geometry; e.g. "
                f"facet {worst} (vertices {fp[worst].round(6).tolist()}) {what}"
                + (
                    f"; no facet lies on it: mesh boundary box {flat.min(axis=0).round(6).tolist()}"
                    f" .. {flat.max(axis=0).round(6).tolist()}, CAD box "
                    f"{self.searcher.bbox_lo.min(axis=0).round(6).tolist()} .. "
                    f"{self.searcher.bbox_hi.max(axis=0).round(6).tolist()} (wrong file, units "
                    "or placement?)"
                    if bad.size == nf
                    else ""
                )
            )
        params = par_t[pos].reshape(-1, nfv, d)[choice]
        params = self._contiguous(root, params)
        return Records(root, params)

    @staticmethod
    def _reduce(key: np.ndarray, par: np.ndarray, dist: np.ndarray):
        """Keep the smallest distance per key; return rows sorted by key."""
        order = np.lexsort((dist, key))
        k = key[order]
        first = np.ones(len(k), dtype=bool)
        first[1:] = k[1:] != k[:-1]
        sel = order[first]
        return key[sel], par[sel], dist[sel]

    # ------------------------------------------------------------------
    def place(
        self, records: Records, straight: npt.ArrayLike
    ) -> tuple[np.ndarray, Records, dict]:
        """Snap facet vertices onto their facets' entities (Kadir 2.2 + 2.3.3).

        Args:
            records: ``root (nf,)`` entity per facet and ``params (nf, nfv, d)``
                seeds (old vertices: their parameters; new vertices: the
                parametric midpoint of the parent edge).
            straight: ``(nf, nfv, 3)`` current (straight) vertex positions.

        Returns:
            ``(points (nf, nfv, 3), records, report)``: projected positions
            (identical for every slot of the same vertex), records with the
            converged parameters (unwrapped relative to the seeds, hence
            contiguous within each facet), and a report with
            ``max_residual``/``mean_residual`` (snap distance ``|S(u) - P|``
            over distinct vertices, length units), ``iterations_histogram``
            (``np.bincount`` of the Newton iterations of the seeded
            projections, one per distinct (vertex, entity, seed)), ``n_points``
            (slots), ``n_vertices``, ``n_fallback``
            (slots whose seeded Newton failed or jumped farther than the
            facet's longest edge), ``n_off_root`` (positions taken from
            another entity) and ``n_unresolved`` (no acceptable projection
            found; the closest point found is used).

        Fallbacks, in order: the other vertices' parameters of the facet and
        their mean as seeds; KD-tree seeds on the facet's entity and on
        entities whose bounding box is within an edge length; a global search.
        """
        st = _facets(straight, "straight")
        root = np.asarray(records.root, dtype=np.int64).reshape(-1)
        params = np.asarray(records.params, dtype=float)
        nf, nfv, _ = st.shape
        d = self.param_dim
        if root.shape != (nf,) or params.shape != (nf, nfv, d):
            raise ValueError(
                f"records (root {root.shape}, params {params.shape}) do not match "
                f"straight {st.shape} (expected root ({nf},), params ({nf}, {nfv}, {d}))"
            )
        if nf and (root.min() < 0 or root.max() >= self.num_entities):
            raise ValueError(f"records.root refers to entities outside 0..{self.num_entities - 1}")
        ns = nf * nfv
        if ns == 0:
            report = {
                "max_residual": 0.0, "mean_residual": 0.0,
                "iterations_histogram": np.zeros(1, dtype=np.int64), "n_points": 0,
                "n_vertices": 0, "n_fallback": 0, "n_off_root": 0, "n_unresolved": 0,
                "n_left_face": 0, "n_edge_vertices": 0, "max_edge_gap": 0.0,
            }
            return np.zeros((nf, nfv, 3)), Records(root.copy(), params.copy()), report
        X = st.reshape(ns, 3)
        ent = np.repeat(root, nfv)
        seed = params.reshape(ns, d)
        hs = np.repeat(_edge_length(st), nfv)
        big = np.finfo(float).max

        acc = self._accept
        # 1. seeded Newton on the facet's entity, once per distinct (entity,
        # vertex, seed): the slots of a vertex shared by several facets of one
        # entity (about 5 per vertex on a surface) mostly carry the same seed
        # and share one result; different seeds (seams, poles, where the
        # parameter is not unique) keep their own Newton run
        uniq, inv, _ = _unique_rows(np.column_stack([ent.astype(float), X, seed]))
        par, proj, dist, its, conv = self.searcher.refine(uniq, ent[uniq], seed[uniq], X,
                                                          self.max_iter)
        par, proj, dist, conv = par[inv], proj[inv], dist[inv], conv[inv]
        valid = conv & (dist <= hs) & np.all(np.isfinite(proj), axis=1)
        n_left_face = 0
        if acc is not None:  # a result beyond the face's trimming loops: fall back
            left = valid & ~acc(ent, par)
            n_left_face = int(left.sum())
            valid &= ~left
        dist = np.where(np.isfinite(dist), dist, big)
        on_root = np.ones(ns, dtype=bool)
        bad = np.flatnonzero(~valid)
        n_fallback = int(bad.size)

        if bad.size:
            # 2. other seeds: the facet's other vertices' params and their mean
            f = bad // nfv
            cand = np.concatenate([params[f], params[f].mean(axis=1, keepdims=True)], axis=1)
            m = nfv + 1
            pt = np.repeat(bad, m)
            cp, cx, cd, _, cc = self.searcher.refine(pt, ent[pt], cand.reshape(-1, d), X, self.max_iter)
            ok = cc & (cd <= hs[pt])
            if acc is not None:
                ok &= acc(ent[pt], cp)
            rows = _best_rows(np.repeat(np.arange(bad.size), m), cd, ok, bad.size)
            hit = rows >= 0
            s, r = bad[hit], rows[hit]
            par[s], proj[s], dist[s], valid[s] = cp[r], cx[r], cd[r], True
            bad = np.flatnonzero(~valid)
        if bad.size:
            # 3. KD-tree seeds on the root entity and on entities whose bbox is near
            lo, hi = self.searcher.bbox_lo, self.searcher.bbox_hi
            Xb, hb = X[bad], hs[bad]
            near = np.all(
                (Xb[:, None, :] >= lo[None] - hb[:, None, None])
                & (Xb[:, None, :] <= hi[None] + hb[:, None, None]),
                axis=2,
            )  # (nb, ne)
            near[np.arange(bad.size), ent[bad]] = True
            bi, be = np.nonzero(near)
            res = self.searcher.search_on(Xb[bi], be, accept=acc)
            qp, qx, qd = res[:3]
            qroot = be == ent[bad][bi]
            qok = qd <= hb[bi]
            if acc is not None:  # only results on the faces (neighbours sharing the edge)
                qok &= res[3]
            r_root = _best_rows(bi, qd, qroot, bad.size)  # best attempt on the root
            r_ok = _best_rows(bi, qd, qok & qroot, bad.size)  # acceptable on the root
            r_any = _best_rows(bi, qd, qok, bad.size)  # acceptable anywhere
            use_root = r_ok >= 0
            use_other = ~use_root & (r_any >= 0)
            s, r = bad[use_root], r_ok[use_root]
            par[s], proj[s], dist[s], valid[s] = qp[r], qx[r], qd[r], True
            s, r = bad[use_other], r_any[use_other]
            proj[s], dist[s], valid[s], on_root[s] = qx[r], qd[r], True, False
            # root parameters of the off-root or still-bad slots: the best root attempt
            upd = ~use_root & (r_root >= 0)
            s, r = bad[upd], r_root[upd]
            closer = ~valid[s] & (qd[r] < dist[s])
            par[s] = np.where((~valid[s] | ~on_root[s])[:, None], qp[r], par[s])
            proj[s[closer]], dist[s[closer]] = qx[r[closer]], qd[r[closer]]
            bad = np.flatnonzero(~valid)
        if bad.size:
            # 4. global search over all entities
            res = self.searcher.search(X[bad], accept=acc)
            ge, gp, gd = res[:3]
            gin = res[3] if acc is not None else np.ones(bad.size, dtype=bool)
            gx = np.empty((bad.size, 3))
            for e in np.unique(ge):  # loop over entities
                s = ge == e
                gx[s] = evaluate_params(self.entities[e], normalize_params(self.entities[e], gp[s]), 0)
            groot = ge == ent[bad]
            gok = gin & (gd <= hs[bad])
            take = gok | (gd < dist[bad])
            s = bad[take]
            proj[s], dist[s], on_root[s] = gx[take], gd[take], groot[take]
            valid[s] = gok[take]
            sr = take & groot
            par[bad[sr]] = gp[sr]
        n_unresolved = int(np.sum(~valid))

        # params: unwrap relative to the seeds (contiguous within the facet);
        # facets with non-finite seeds relative to their first vertex
        par = self._unwrap(ent, par, seed)
        nanf = ~np.all(np.isfinite(seed).reshape(nf, -1), axis=1)
        if nanf.any():
            pf = par.reshape(nf, nfv, d)
            sub = pf[nanf]
            ref = np.repeat(sub[:, :1], nfv, axis=1).reshape(-1, d)
            pf[nanf] = self._unwrap(np.repeat(root[nanf], nfv), sub.reshape(-1, d), ref).reshape(-1, nfv, d)
            par = pf.reshape(ns, d)
        # one position per mesh vertex: the best slot's
        gid = _groups(X, MERGE_RTOL * self.size)
        order = np.lexsort((dist, ~on_root, ~valid, gid))
        g_sorted = gid[order]
        first = np.ones(ns, dtype=bool)
        first[1:] = g_sorted[1:] != g_sorted[:-1]
        rep_of_group = np.empty(int(gid.max()) + 1 if ns else 0, dtype=np.int64)
        rep_of_group[g_sorted[first]] = order[first]
        rep = rep_of_group[gid]
        # same entity but a different position than the representative: take its params
        off = (ent == ent[rep]) & (np.linalg.norm(proj - proj[rep], axis=1) > 1e-9 * self.size)
        if off.any():
            par[off] = self._unwrap(ent[off], par[rep[off]], seed[off])
        proj = proj[rep]
        # vertices on facets of several entities lie on the faces' common edge
        n_edge, edge_gap = self._edge_vertices(gid, ent, proj, par, seed, X, hs)
        dist = np.linalg.norm(proj - X, axis=1)
        vd = dist[rep_of_group]  # one value per distinct vertex

        report = {
            "max_residual": float(vd.max()) if vd.size else 0.0,
            "mean_residual": float(vd.mean()) if vd.size else 0.0,
            "iterations_histogram": np.bincount(its, minlength=1),
            "n_points": int(ns),
            "n_vertices": int(vd.size),
            "n_fallback": n_fallback,
            "n_off_root": int(np.sum(~on_root)),
            "n_unresolved": n_unresolved,
            "n_left_face": n_left_face,
            "n_edge_vertices": n_edge,
            "max_edge_gap": edge_gap,
        }
        return proj.reshape(nf, nfv, 3), Records(root.copy(), par.reshape(nf, nfv, d)), report

    def _normals(self, ent: np.ndarray, params: np.ndarray) -> np.ndarray:
        """Unit normals ``(n, 3)`` of surfaces (zero where degenerate); curves: zero."""
        out = np.zeros((len(ent), 3))
        if self.param_dim != 2:
            return out
        for e in np.unique(ent):  # loop over entities
            sel = np.flatnonzero(ent == e)
            ent_e = self.entities[e]
            _, T = evaluate_params(ent_e, normalize_params(ent_e, params[sel]), 1)
            c = np.cross(T[:, 0], T[:, 1])
            n = np.linalg.norm(c, axis=1)
            lengths = np.diff(ent_e.bounds, axis=1)[:, 0]
            ok = n > (DEGENERATE_RTOL * ent_e.bbox_size) ** 2 / (lengths[0] * lengths[1])
            out[sel[ok]] = c[ok] / n[ok, None]
        return out

    def _edge_vertices(
        self, gid: np.ndarray, ent: np.ndarray, proj: np.ndarray, par: np.ndarray,
        seed: np.ndarray, X: np.ndarray, hs: np.ndarray,
    ) -> tuple[int, float]:
        """Put vertices shared by facets of several entities onto all of them.

        A mesh vertex on facets of entities ``A`` and ``B`` lies on the CAD edge
        the two faces share.  Its projections onto ``A`` and ``B`` separately
        are on one face each but off the edge by ``O(h^2)`` (e.g. the midpoint
        of a chord of a circular edge between a plane and a cylinder projects
        onto the plane inside the hole).  Gauss-Newton steps converge to the
        edge: project ``x`` onto every entity of the vertex (seeded Newton),
        move ``x`` to the nearest point of the intersection of the tangent
        planes there (``n_i . (y - p_i) = 0``, least squares, step capped to
        the local edge length), repeat.  The best point over
        :data:`EDGE_SWEEPS` steps is used if it is nearer all the entities
        than the start and within the local edge length of the straight
        vertex.  Every slot then takes the parameters of that point on its own
        entity.  (Between faces meeting tangentially the step is ill-posed;
        the gap left there is second order in the distance to the edge.)

        Updates ``proj (ns, 3)`` (one position per group already) and
        ``par (ns, d)`` in place; returns ``(number of edge vertices, largest
        distance of an edge vertex to one of its entities)``.
        """
        ne = self.num_entities
        if len(gid) == 0:
            return 0, 0.0
        key = gid * ne + ent
        ukey, first_slot, inv = np.unique(key, return_index=True, return_inverse=True)
        inv = inv.reshape(-1)
        ug = ukey // ne
        cnt = np.bincount(ug)
        pidx = np.flatnonzero(cnt[ug] > 1)  # (group, entity) pairs of edge vertices
        if pidx.size == 0:
            return 0, 0.0
        m = pidx.size
        pe = ukey[pidx] % ne
        groups, gpos = np.unique(ug[pidx], return_inverse=True)
        gpos = gpos.reshape(-1)
        G = groups.size
        start = np.searchsorted(gpos, np.arange(G))  # pairs are sorted by group
        rank = np.arange(m) - start[gpos]
        gslot = first_slot[pidx][start]  # one slot per edge vertex
        x = proj[gslot].copy()
        hg = np.zeros(G)
        sl = np.flatnonzero(np.isin(gid, groups))
        np.maximum.at(hg, np.searchsorted(groups, gid[sl]), hs[sl])
        etol = EDGE_RTOL * self.size

        def distances(x, seeds):
            pp, px, pd, _, _ = self.searcher.refine(np.arange(m), pe, seeds, x[gpos], self.max_iter)
            score = np.zeros(G)
            np.maximum.at(score, gpos, pd)
            return pp, px, score

        pp, px, score = distances(x, par[first_slot[pidx]])
        pp0, score0 = pp.copy(), score.copy()
        best_x, best_pp, best = x.copy(), pp.copy(), score.copy()
        todo = best > etol
        mr = int(rank.max()) + 1
        for _sweep in range(EDGE_SWEEPS):
            if not todo.any():
                break
            # Gauss-Newton: the point nearest x on the intersection of the entities'
            # tangent planes at x's projections, n_i . (y - p_i) = 0
            nrm = self._normals(pe, pp)  # (m, 3), zero where degenerate (pole)
            N = np.zeros((G, mr, 3))
            N[gpos, rank] = nrm
            res = np.zeros((G, mr))
            res[gpos, rank] = np.einsum("ij,ij->i", nrm, x[gpos] - px)
            gram = np.einsum("gij,gkj->gik", N, N)
            gram[:, np.arange(mr), np.arange(mr)] += 1e-12 + (np.linalg.norm(N, axis=2) == 0)
            lam = np.linalg.solve(gram, res[:, :, None])[:, :, 0]
            step = np.einsum("gi,gij->gj", lam, N)
            sl_ = np.linalg.norm(step, axis=1)
            step *= np.minimum(1.0, hg / np.maximum(sl_, 1e-300))[:, None]
            x = np.where(todo[:, None], x - step, x)
            pp, px, score = distances(x, pp)
            better = todo & (score < best)
            best_x[better], best[better] = x[better], score[better]
            best_pp[better[gpos]] = pp[better[gpos]]
            todo &= best > etol
        keep = (best < score0) & (np.linalg.norm(best_x - X[gslot], axis=1) <= hg)
        x_fin = np.where(keep[:, None], best_x, proj[gslot])
        pp_fin = np.where(keep[gpos][:, None], best_pp, pp0)
        gap = np.where(keep, best, score0)
        # write back: every slot of an edge vertex
        pos = np.full(len(ukey), -1, dtype=np.int64)
        pos[pidx] = np.arange(m)
        ps = pos[inv]
        s = np.flatnonzero(ps >= 0)
        proj[s] = x_fin[gpos[ps[s]]]
        par[s] = self._unwrap(ent[s], pp_fin[ps[s]], par[s])
        return int(G), float(gap.max())


def _best_rows(group: np.ndarray, score: np.ndarray, mask: np.ndarray, n: int) -> np.ndarray:
    """Per group ``0..n-1``: row with the smallest ``score`` among ``mask``, or -1."""
    out = np.full(n, -1, dtype=np.int64)
    rows = np.flatnonzero(mask)
    if rows.size:
        order = rows[np.lexsort((score[rows], group[rows]))]
        g, first = np.unique(group[order], return_index=True)
        out[g] = order[first]
    return out


def _ramp(counts: np.ndarray) -> np.ndarray:
    """``[0..c0-1, 0..c1-1, ...]`` for counts ``c`` (vectorised)."""
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    starts = np.cumsum(counts) - counts
    return np.arange(total) - np.repeat(starts, counts)
