"""CadGeometry: snap boundary vertices onto the faces, edges and vertices of a CAD model.

:class:`CadGeometry` is the snapping geometry of Kadir (2010), chapter 2, on
the B-rep of a CAD file (:meth:`CadGeometry.from_file`: STEP, IGES or BREP
through OpenCASCADE) or on bare NURBS entities:

* :meth:`CadGeometry.attach` initialises the coarse mesh (Kadir 2.3.1): each
  boundary facet gets ONE entity (face in 3D, edge curve in 2D) on which all
  its vertices lie (Kadir 2.3.4) and the parameters of its vertices there
  (the ``(n, u)`` / ``(n, u, v)`` tuples of Kadir 2.3.2), stored per facet in
  :class:`nagata_snap.mesh.records.Records`.  The entity is known when the mesh
  came from the CAD (``faces``, or the gmsh classification recorded with
  :meth:`CadGeometry.set_mesh_hints`), which costs one projection per
  vertex; otherwise a global search finds it: every entity whose bounding
  box holds the vertex (within the tolerance) is a candidate, analytic faces
  project in closed form, NURBS faces by Newton from their own search
  samples, trimmed faces only count within their loops
  (:class:`~nagata_snap.cad.trimming.TrimLoops`), and each facet takes the
  entity nearest to all its vertices.
* :meth:`CadGeometry.place` snaps after a refinement (Kadir 2.2, Algorithm 1,
  neighbour seeds of 2.3.3): each vertex is projected onto its facet's
  entity, seeded with the record's parameters (for a new vertex the
  parametric midpoint of its parent edge; seam-aware).

CAD edges and corners (3D models with topology).  A mesh edge whose two
boundary facets lie on different faces runs along the CAD edge they share;
:meth:`attach` records that for each facet edge (over all MPI processes)
and stores it in extra record channels that the lineage refines exactly:
``params[..., 2 + m] = f_m (1 - lambda_m)`` for the facet's coarse edge
``m`` (opposite coarse vertex ``m``), where ``f_m`` is 1 if that edge is on a
CAD edge and ``lambda`` are the barycentric coordinates in the coarse
facet.  Barycentric combinations (the refinement's weights 0, 1/2, 1) keep
these values exact, and a vertex is on coarse edge ``m`` of a flagged edge
exactly when its channel ``m`` equals 1.  Such a vertex is projected onto
the nearest edge curve of its face (closed form for lines and circles,
Newton for NURBS); a corner goes to the nearest CAD vertex of its face.  A
vertex is a corner if one of its facets has two flagged edges there, if its
facets together lie on three or more faces or on two or more distinct edge
curves, or if it is on a flagged edge and its record puts it at a CAD vertex
(the mesher's node there, e.g. the end of a seam on a closed edge); one rule
for :meth:`place` and :meth:`project` (:meth:`_merge`), so a corner never
moves along one of its edges.  Every facet then takes
the ``(u, v)`` of that point on its own face.  All processes that hold a
facet of the vertex compute the same point, so sharp edges stay sharp after
any number of levels and in parallel.  Geometries built from bare entities
(no topology) fall back to putting a vertex shared by facets of several
entities on the process onto all of them (alternating Gauss-Newton steps).

Parameters in closed (periodic) directions are kept *unwrapped per facet*:
the vertices of one facet never differ by a jump of a period, so parametric
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
facets' vertices (``mesh.geometry.x[...]``); the ``Snapper`` hook calls
``attach`` once on the coarse mesh and ``place`` after every refinement.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from nagata_snap.cad.projection import (
    GlobalSearcher,
    entity_periods,
    evaluate_params,
    is_analytic,
    normalize_params,
)
from nagata_snap.cad.trimming import TRIM_RTOL, TrimLoops
from nagata_snap.geometry import PlaceReport
from nagata_snap.mesh.arrays import best_per_group
from nagata_snap.mesh.corners import corner_vertices
from nagata_snap.mesh.records import Records

__all__ = ["CadError", "CadGeometry", "TrimLoops"]

#: two facet vertices closer than this (relative to the model size) are one vertex
MERGE_RTOL = 1e-10
#: a parameter direction is degenerate at a point (pole) if ``|dS/dp|`` is below
#: this fraction of the entity size (per unit parameter)
DEGENERATE_RTOL = 1e-9
#: an edge vertex (on facets of several entities) counts as on all of them within
#: this fraction of the model size
EDGE_RTOL = 1e-14
#: alternating-projection sweeps that bring an edge vertex onto all its entities
#: (geometries without topology)
EDGE_SWEEPS = 8
#: step of the parameter nudge that gives normals at degenerate points (poles,
#: apexes), as a fraction of the way to the facet's parametric centre
NORMAL_NUDGE = 1e-6


class CadError(RuntimeError):
    """The mesh boundary does not match the CAD geometry, or the CAD file cannot be used."""


# ----------------------------------------------------------------------
# array helpers
# ----------------------------------------------------------------------
def _facets(a: npt.ArrayLike, what: str) -> np.ndarray:
    x = np.asarray(a, dtype=float)
    if x.ndim != 3 or x.shape[2] not in (2, 3) or x.shape[1] < 1:
        raise ValueError(f"{what} must have shape (nf, nfv, 3), got {x.shape}")
    if x.shape[2] == 2:
        x = np.concatenate([x, np.zeros((*x.shape[:2], 1))], axis=2)
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
    """Distinct rows of ``a (n, k)`` (float or int): ``(first (m,), inverse (n,), rows (m, k))``.

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


def _ramp(counts: np.ndarray) -> np.ndarray:
    """``[0..c0-1, 0..c1-1, ...]`` for counts ``c`` (vectorised)."""
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    starts = np.cumsum(counts) - counts
    return np.arange(total) - np.repeat(starts, counts)


#: singular values of the stacked face normals below this fraction of the largest are
#: dropped in the intersection steps (faces meeting at less than ~1 degree)
TANGENT_RCOND = 2e-2


def _truncated_lstsq(N: np.ndarray, res: np.ndarray, rcond: float = TANGENT_RCOND) -> np.ndarray:
    """Minimum-norm ``y (G, 3)`` with ``N y ~ res`` per group, small singular values dropped.

    ``N (G, m, 3)`` stacked unit normals (zero rows ignored), ``res (G, m)``.
    """
    U, sv, Vt = np.linalg.svd(N, full_matrices=False)  # (G, m, k), (G, k), (G, k, 3)
    keep = sv > rcond * sv[:, :1]
    inv = np.where(keep, 1.0 / np.where(keep, sv, 1.0), 0.0)
    coef = np.einsum("gmk,gm->gk", U, res) * inv
    return np.einsum("gk,gkj->gj", coef, Vt)


def _row_index(rows: np.ndarray) -> np.ndarray:
    """``(n,)`` id of each row of ``rows (n, k)`` (equal rows, equal ids; ids ``0..m-1``)."""
    if len(rows) == 0:
        return np.zeros(0, dtype=np.int64)
    return _unique_rows(rows)[1].astype(np.int64, copy=False)


def _box_pairs(points: np.ndarray, tol: np.ndarray, lo: np.ndarray, hi: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """``(point, box)`` pairs with the point inside the box inflated by the point's ``tol``.

    A KD-tree of the points answers one ball query per box (its circumsphere
    plus the largest tolerance), then the boxes are tested exactly.
    """
    if len(points) == 0 or len(lo) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    tree = cKDTree(points)
    centre, radius = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo, axis=1) + tol.max()
    hits = tree.query_ball_point(centre, radius)
    box = np.repeat(np.arange(len(lo)), [len(h) for h in hits])
    pt = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits]) if len(box) else \
        np.zeros(0, dtype=np.int64)
    t = tol[pt][:, None]
    ok = np.all((points[pt] >= lo[box] - t) & (points[pt] <= hi[box] + t), axis=1)
    return pt[ok], box[ok]


class _Ragged:
    """Integer lists of different lengths as one flat array with offsets (CSR).

    ``take(rows)`` gathers many rows at once without a Python loop over them.
    """

    def __init__(self, lists: list):
        self.counts = np.array([len(a) for a in lists], dtype=np.int64)
        self.ptr = np.concatenate([[0], np.cumsum(self.counts)]).astype(np.int64)
        self.flat = np.concatenate([np.asarray(a, dtype=np.int64) for a in lists] + [np.zeros(0, np.int64)])

    def take(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(counts (k,), values (counts.sum(),))``: the rows ``rows (k,)``, concatenated in order."""
        cnt = self.counts[rows]
        return cnt, self.flat[np.repeat(self.ptr[rows], cnt) + _ramp(cnt)]


class _Topology:
    """Edges and vertices of a 3D model, as arrays over the geometry's faces.

    Attributes:
        curves: 3D curves of the non-degenerate edges (their order = curve index).
        curve_of_edge: ``(ne,)`` curve index of each model edge (-1 if degenerate).
        face_curves: per face: curve indices of its edges (:class:`_Ragged`).
        face_vertices: per face: indices into :attr:`points` of its CAD vertices (:class:`_Ragged`).
        points: ``(nv, 3)`` CAD vertices.
        feature_faces: the faces of each curve's edge (rows ``0..nc-1``), then
            the faces around each CAD vertex (rows ``nc + v``) (:class:`_Ragged`).
        searcher: closest points on given edges (closed form / Newton).
    """

    def __init__(self, model):
        edges = model.edges
        self.curve_of_edge = np.full(len(edges), -1, dtype=np.int64)
        self.curves = []
        for i, e in enumerate(edges):
            if e.curve is not None:
                self.curve_of_edge[i] = len(self.curves)
                self.curves.append(e.curve)
        self.points = model.vertices
        face_curves, face_vertices = [], []
        for f in model.faces:  # loop over CAD faces (set-up)
            c = self.curve_of_edge[f.edges]
            face_curves.append(c[c >= 0])
            face_vertices.append(sorted({v for e in f.edges for v in edges[e].vertices if v >= 0}))
        curve_faces = [edges[i].faces for i in np.flatnonzero(self.curve_of_edge >= 0)]
        around: list[set] = [set() for _ in range(len(self.points))]
        for f, vs in enumerate(face_vertices):
            for v in vs:
                around[v].add(f)
        self.face_curves, self.face_vertices = _Ragged(face_curves), _Ragged(face_vertices)
        self.feature_faces = _Ragged(curve_faces + [sorted(a) for a in around])
        self.searcher = GlobalSearcher(self.curves) if self.curves else None
        if self.curves:
            self.lo = np.array([c.bbox[0] for c in self.curves])
            self.hi = np.array([c.bbox[1] for c in self.curves])


class _PerEntity:
    """``f(i)`` for ``i < n`` as a read-only sequence, evaluated when indexed (lazy per-entity data)."""

    def __init__(self, n: int, f):
        self._n, self._f = n, f

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i: int):
        return self._f(i)


class CadGeometry:
    """Snapping geometry from a CAD model or from NURBS curves (2D) / surfaces (3D).

    Args:
        entities: the CAD entities, all curves (2D meshes: boundary segments
            are snapped to curves) or all surfaces (3D: triangles to surfaces):
            :class:`~nagata_snap.cad.nurbs.NurbsCurve` /
            :class:`~nagata_snap.cad.nurbs.NurbsSurface`, or the analytic
            :mod:`~nagata_snap.cad.curves` / :mod:`~nagata_snap.cad.surfaces`.
        trim_loops: surfaces only: per entity the outer trimming loop, a
            ``(k, 2)`` polygon in its ``(u, v)`` parameters, or ``None`` (the
            whole surface is the face).
        trim_holes: surfaces only: per entity a list of inner loops.
        tol_factor: :meth:`attach` accepts a facet if all its vertices are
            within ``tol_factor * h`` of one entity, ``h`` the facet's longest
            edge (dimensionless).
        k_seeds: nearest grid samples used as Newton seeds in searches on NURBS.
        max_iter: Newton iterations per projection in :meth:`place`.
        per_span: samples per knot span and direction of the search grid.
        trim_rtol: absolute trimming tolerance, relative to each surface's size
            (see :class:`~nagata_snap.cad.trimming.TrimLoops`).
        model: a :class:`~nagata_snap.cad.topology.CadModel` whose faces
            (3D) or edges (2D) the entities are: its trimming loops and its
            edges and vertices (topology) are used.  Use :meth:`from_model` /
            :meth:`from_file`.

    Raises:
        ValueError: empty or mixed entity list, trimming loops for curves or of
            the wrong count.
    """

    #: facet tags ``Snapper`` snaps by default (:func:`~nagata_snap.cad.meshed.mesh_cad`
    #: sets the exterior faces'); None: all tags
    tags: list[int] | None = None

    def __init__(
        self,
        entities: Sequence,
        trim_loops: Sequence[np.ndarray | None] | None = None,
        trim_holes: Sequence[Sequence[np.ndarray] | None] | None = None,
        *,
        tol_factor: float = 1e-2,
        k_seeds: int = 6,
        max_iter: int = 20,
        per_span: int | None = None,
        trim_rtol: float = TRIM_RTOL,
        model=None,
    ):
        entities = list(entities)
        if not entities:
            raise ValueError("CadGeometry needs at least one curve or surface")
        dims = {getattr(e, "param_dim", None) for e in entities}
        if len(dims) != 1 or dims.pop() not in (1, 2):
            raise ValueError(
                "entities must be all curves or all surfaces, got "
                f"{sorted({type(e).__name__ for e in entities})}"
            )
        self.entities = entities
        self.param_dim = entities[0].param_dim
        self.tol_factor = float(tol_factor)
        self.max_iter = int(max_iter)
        self.model = model
        self.trims = self._trims(trim_loops, trim_holes, trim_rtol)
        extra = None if self.trims is None else _PerEntity(len(entities), self.trims.loop_points)
        filt = None if self.trims is None else (  # search samples inside the loops only
            lambda e, P: self.trims.inside(np.full(len(P), e), P, band=False))
        self.searcher = GlobalSearcher(entities, per_span=per_span, k_seeds=k_seeds,
                                       sample_filter=filt, extra_samples=extra)
        self.size = self.searcher.size
        self._period = np.array([entity_periods(e) for e in entities])
        #: ``(n_entities,)`` bool: closed-form projection (no seeds needed)
        self._analytic = np.array([is_analytic(e) for e in entities], dtype=bool)
        self.topology = _Topology(model) if model is not None and self.param_dim == 2 else None
        #: channels per facet vertex in the records: the parameters, plus in 3D with
        #: topology the three CAD-edge channels
        self.record_width = self.param_dim + (3 if self.topology is not None else 0)
        self._hints = None

    def _trims(self, trim_loops, trim_holes, rtol) -> TrimLoops | None:
        n = len(self.entities)
        for name, arr in (("trim_loops", trim_loops), ("trim_holes", trim_holes)):
            if arr is not None and len(arr) != n:
                raise ValueError(f"{name} has {len(arr)} entries for {n} entities")
        if self.model is not None and self.param_dim == 2:
            loops = [[lp.points for lp in f.loops] for f in self.model.faces]
            bands = [[lp.band for lp in f.loops] for f in self.model.faces]
            return TrimLoops(self.entities, loops, bands, rtol) if any(loops) else None
        has = any(t is not None for t in (trim_loops or [])) or any(h for h in (trim_holes or []))
        if not has:
            return None
        if self.param_dim != 2:
            raise ValueError("trimming loops apply to surfaces only")
        return TrimLoops.from_outer_holes(self.entities, trim_loops, trim_holes, rtol)

    # ------------------------------------------------------------------
    # construction from CAD files
    # ------------------------------------------------------------------
    @classmethod
    def from_model(cls, model, *, dim: int | None = None, **kwargs) -> CadGeometry:
        """Geometry of a :class:`~nagata_snap.cad.topology.CadModel`.

        Args:
            model: the model.
            dim: mesh dimension: 3 snaps onto the faces, 2 onto the edge
                curves (a planar profile in ``z = 0``); ``None``: 2 if every
                face is such a plane (or there are only curves), else 3.
            **kwargs: passed to :class:`CadGeometry`.

        Raises:
            CadError: no face (3D) or no edge curve (2D) in the model.
        """
        if dim is None:
            dim = 2 if model.is_planar_2d() else 3
        if dim not in (2, 3):
            raise ValueError(f"dim must be 2, 3 or None, got {dim!r}")
        where = model.path or "the CAD model"
        if dim == 3:
            if not model.faces:
                raise CadError(f"{where}: no faces to snap a 3D mesh onto (the shape has "
                               f"{len(model.curve_edges())} edges only)")
            return cls([f.surface for f in model.faces], model=model, **kwargs)
        curves = model.curve_edges()
        if curves.size == 0:
            raise CadError(f"{where}: no edge curves to snap a 2D mesh onto")
        geo = cls([model.edges[e].curve for e in curves], model=model, **kwargs)
        geo._curve_edges = curves  # model edge of each entity
        return geo

    @classmethod
    def from_file(
        cls,
        path: str | os.PathLike,
        *,
        dim: int | None = None,
        unit: str = "MM",
        heal: bool = True,
        isolate: bool = True,
        timeout: float | None = None,
        comm=None,
        **kwargs,
    ) -> CadGeometry:
        """Geometry of a STEP (``.step/.stp``), IGES (``.igs/.iges``) or BREP file.

        The file is read by OpenCASCADE (:mod:`nagata_snap.cad.read`):
        healed with ``ShapeFix_Shape`` (faces that share no edge, as in most
        IGES files, are sewn first), analytic faces kept analytic, every
        other face converted to NURBS, trimming loops from the p-curves.

        Args:
            path: the file.
            dim: 2 or 3 (see :meth:`from_model`).
            unit: length unit of the geometry (STEP and IGES coordinates are
                converted to it from the file's unit, as OpenCASCADE and gmsh
                do: their default, and this one, is millimetres ``"MM"``; use
                the same as gmsh's ``Geometry.OCCTargetUnit`` for the mesh);
                ``"FILE"``: the file's own unit.  BREP files have no unit.
            heal: run OpenCASCADE's shape healing.
            isolate: read in a child process (:mod:`nagata_snap.cad.worker`),
                so that a file that crashes or hangs OpenCASCADE raises
                :class:`CadError` instead of killing this process.
            timeout: seconds allowed for reading (default: 60 s plus 30 s per MB).
            comm: an MPI communicator: the file is read on its rank 0 only and
                the model broadcast.
            **kwargs: passed to :class:`CadGeometry`.

        Raises:
            CadError: the file cannot be read (the message names it and says
                why: OpenCASCADE's status, an empty shape, a face that cannot
                be converted, a crash or time-out of the reader), or holds no
                entity of the kind needed.
        """
        from nagata_snap.cad.topology import CadModel
        from nagata_snap.cad.worker import read_cad

        data, err = None, None
        if comm is None or comm.rank == 0:
            try:
                data = read_cad(path, unit=unit, heal=heal, isolate=isolate, timeout=timeout)
            except CadError as e:
                err = str(e)
        if comm is not None:
            data, err = comm.bcast((data, err), root=0)
        if err is not None:
            raise CadError(err)
        try:
            model = CadModel.from_data(data)
            return cls.from_model(model, dim=dim, **kwargs)
        except ValueError as e:  # geometry OpenCASCADE accepted but that cannot be used
            msg = str(e)
            raise CadError(msg if os.fspath(path) in msg or data["path"] in msg
                           else f"{data['path']}: {msg}") from None

    @classmethod
    def from_iges(cls, path: str | os.PathLike, *, dim: int | None = None, unit: str = "FILE",
                  **kwargs) -> CadGeometry:
        """Geometry of an IGES file: :meth:`from_file`, by default in the file's own unit."""
        return cls.from_file(path, dim=dim, unit=unit, **kwargs)

    # ------------------------------------------------------------------
    # basic queries
    # ------------------------------------------------------------------
    @property
    def num_entities(self) -> int:
        """Number of CAD entities (faces in 3D, curves in 2D)."""
        return len(self.entities)

    @property
    def _accept(self):
        """``f(ent, params) -> bool`` (on the trimmed face), or ``None`` without trims."""
        return None if self.trims is None else self.trims.inside

    def inside(self, ent: npt.ArrayLike, params: npt.ArrayLike) -> np.ndarray:
        """``(n,)`` bool: ``params (n, d)`` of entity ``ent (n,)`` lie on its (trimmed) face."""
        ent = np.asarray(ent, dtype=np.int64).reshape(-1)
        if self.trims is None:
            return np.ones(len(ent), dtype=bool)
        return self.trims.inside(ent, np.asarray(params, dtype=float).reshape(len(ent), -1)[:, :2])

    def evaluate(self, root: npt.ArrayLike, params: np.ndarray) -> np.ndarray:
        """Points of records: entity ``root (nf,)`` at ``params (nf, nfv, >= d)`` -> ``(nf, nfv, 3)``.

        Parameters are wrapped into each entity's period (NURBS: clamped to the
        knot domain); channels beyond the ``d`` parameters are ignored.
        """
        root = np.asarray(root, dtype=np.int64).reshape(-1)
        params = np.asarray(params, dtype=float)
        nf, nfv, _ = params.shape
        d = self.param_dim
        out = np.empty((nf, nfv, 3))
        for e in np.unique(root):  # loop over entities
            sel = root == e
            p = normalize_params(self.entities[e], params[sel][:, :, :d].reshape(-1, d))
            out[sel] = evaluate_params(self.entities[e], p, 0).reshape(-1, nfv, 3)
        return out

    def closest_point(self, points: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest point of each point on the (trimmed) faces: global search.

        Newton from the ``k_seeds`` nearest grid samples (samples on the faces
        only; analytic faces in closed form); a result on a surface's
        extension beyond its face's trimming loops does not count.

        Returns:
            ``(entity (n,) int64, params (n, d), distance (n,))``; entity ``-1``
            and distance ``inf`` where no seed converged onto a face.
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
    # parameters
    # ------------------------------------------------------------------
    def _unwrap(self, root: np.ndarray, params: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """Shift ``params (n, d)`` by whole periods to be nearest to ``ref (n, d)``."""
        per = self._period[root]  # (n, d), nan where open
        use = np.isfinite(per) & np.isfinite(ref)
        shift = np.round((np.where(use, ref, 0.0) - params) / np.where(use, per, 1.0))
        return params + np.where(use, shift * per, 0.0)

    def _degenerate(self, root: np.ndarray, params: np.ndarray) -> np.ndarray:
        """``(n, d)`` bool: tangent ``dS/dp_a`` vanishes (e.g. the poles of a sphere)."""
        n, d = params.shape
        out = np.zeros((n, d), dtype=bool)
        for e in np.unique(root):  # loop over entities
            ent = self.entities[e]
            if not getattr(ent, "can_degenerate", True):  # no pole, apex or collapsed edge
                continue
            sel = np.flatnonzero(root == e)
            p = normalize_params(ent, params[sel])
            _, T = evaluate_params(ent, p, 1)
            lengths = np.diff(ent.bounds, axis=1)[:, 0]  # (d,)
            thr = DEGENERATE_RTOL * ent.bbox_size / np.maximum(lengths, 1e-300)
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
            closed = np.isfinite(per)
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

    def _project(self, ent: np.ndarray, X: np.ndarray, seeds: np.ndarray):
        """Seeded projection of ``X (n, 3)`` onto entities ``ent (n,)``, one run per distinct
        (entity, point, seed): ``(params, points, dist, iterations, converged)``."""
        d = self.param_dim
        if len(ent) == 0:
            z = np.zeros(0)
            return np.zeros((0, d)), np.zeros((0, 3)), z, z.astype(np.int64), z.astype(bool)
        uniq, inv, _ = _unique_rows(np.column_stack([ent.astype(float), X, seeds]))
        par, proj, dist, its, conv = self.searcher.refine(uniq, ent[uniq], seeds[uniq], X, self.max_iter)
        return par[inv], proj[inv], dist[inv], its, conv[inv]

    def _unpack(self, records: Records, points: npt.ArrayLike, what: str):
        """Validated ``(points (nf, nfv, 3), root (nf,), params (nf, nfv, d), channels)``."""
        st = _facets(points, what)
        root = np.asarray(records.root, dtype=np.int64).reshape(-1)
        params = np.asarray(records.params, dtype=float)
        nf, nfv, _ = st.shape
        d, w = self.param_dim, self.record_width
        if root.shape != (nf,) or params.ndim != 3 or params.shape[:2] != (nf, nfv) or \
                params.shape[2] not in (d, w):
            raise ValueError(
                f"records (root {root.shape}, params {params.shape}) do not match {what} "
                f"{st.shape} (expected root ({nf},), params ({nf}, {nfv}, {w}))"
            )
        if nf and (root.min() < 0 or root.max() >= self.num_entities):
            raise ValueError(f"records.root refers to entities outside 0..{self.num_entities - 1}")
        chan = params[:, :, d:] if params.shape[2] == w and w > d else np.zeros((nf, nfv, w - d))
        return st, root, params[:, :, :d], chan

    # ------------------------------------------------------------------
    # attach: records of the coarse mesh
    # ------------------------------------------------------------------
    def attach(
        self,
        facet_points: npt.ArrayLike,
        nodes: npt.ArrayLike | None = None,
        *,
        faces: npt.ArrayLike | None = None,
        seeds: npt.ArrayLike | None = None,
        comm=None,
    ) -> Records:
        """Records of the coarse mesh's boundary facets (Kadir 2.3.1).

        Args:
            facet_points: ``(nf, nfv, 3)`` vertex coordinates of the boundary
                facets to snap (2D: ``nfv = 2`` segments in the z = 0 plane,
                matched to curves; 3D: ``nfv = 3`` triangles, matched to surfaces).
            nodes: optional ``(nf, nfv)`` global vertex ids (vertex identity;
                with :meth:`set_mesh_hints` also the key of the mesher's
                facets); by default vertices are identified by their
                coordinates.
            faces: optional ``(nf,)`` entity of each facet (e.g. the CAD face
                gmsh generated it on): no search.
            seeds: optional ``(nf, nfv, d)`` parameters of the vertices on
                those entities (Newton seeds; NaN where unknown).
            comm: MPI communicator of the mesh (collective): CAD-edge channels
                of facet edges shared across processes are then exact.

        Returns:
            :class:`Records`: ``root (nf,)`` int64 entity per facet;
            ``params (nf, nfv, record_width)``: the vertices' parameters on it,
            unwrapped per facet in closed directions (and in 3D with topology
            the CAD-edge channels, see the module docstring).

        Raises:
            CadError: a facet has a vertex farther than ``tol_factor * h`` (``h``
                its longest edge) from its entity (or from every entity); the
                message names the facet and the distance.
        """
        err, out = None, None
        try:
            out = self._attach_local(facet_points, nodes, faces, seeds)
        except Exception as e:  # raised after the collective exchange below
            err = e
        if self.topology is None:
            if err is not None:
                raise err
            return out[0]
        keys = None if err is not None else out[1]
        if comm is not None and comm.size > 1:
            every = comm.allgather(keys)
            if err is not None:
                raise err
            if any(k is None for k in every):
                raise CadError("attach failed on another process")
            allkeys = np.concatenate(list(every))
        else:
            if err is not None:
                raise err
            allkeys = keys
        records = out[0]
        channels = self._edge_channels(keys, allkeys, records.params.shape[1])
        records.params = np.concatenate([records.params, channels], axis=2)
        return records

    def _attach_local(self, facet_points, nodes, faces, seeds):
        """Records without CAD-edge channels, and the facet-edge keys ``(3 nf, 3)``."""
        fp = _facets(facet_points, "facet_points")
        nf, nfv, _ = fp.shape
        d = self.param_dim
        if nfv - 1 != d:
            have = "curves" if d == 1 else "surfaces"
            need = "curves (2D mesh, segment facets)" if nfv == 2 else "surfaces (3D mesh, triangle facets)"
            raise CadError(
                f"facets with {nfv} vertices need {need}; this CadGeometry has {have} "
                "(CadGeometry.from_file(path, dim=...) picks the kind)"
            )
        flat = fp.reshape(-1, 3)
        gid_input = None if nodes is None else np.asarray(nodes, dtype=np.int64).reshape(nf, nfv)
        gid = _groups(flat, MERGE_RTOL * self.size, gid_input).reshape(nf, nfv) if nf else \
            np.zeros((0, nfv), dtype=np.int64)
        h = _edge_length(fp)
        tol = self.tol_factor * h
        if nf == 0:
            root, params = np.zeros(0, dtype=np.int64), np.zeros((0, nfv, d))
        else:
            if faces is None and self._hints is not None and gid_input is not None:
                faces, seeds = self._hinted(gid_input)
            if faces is None:
                root, params, score = self._search_faces(fp, gid, tol)
            else:
                root, params, score = self._on_faces(fp, gid, faces, seeds)
            self._check_attached(fp, root, score, tol, h, given=faces is not None)
            params = self._contiguous(root, params)
        keys = None
        if self.topology is not None:
            ids = gid_input if gid_input is not None else gid
            loc = np.array([[1, 2], [2, 0], [0, 1]])  # facet edge m is opposite vertex m
            a, b = ids[:, loc[:, 0]], ids[:, loc[:, 1]]
            keys = np.stack([np.minimum(a, b).ravel(), np.maximum(a, b).ravel(),
                             np.repeat(root, 3)], axis=1)
        return Records(root, params), keys

    def _check_attached(self, fp, root, score, tol, h, given: bool) -> None:
        bad = np.flatnonzero(~(score <= tol))
        if not bad.size:
            return
        nf = len(fp)
        flat = fp.reshape(-1, 3)
        worst = bad[np.argmax(np.where(np.isfinite(score[bad]), score[bad], np.inf) / np.maximum(h[bad], 1e-300))]
        what = (
            f"is {score[worst]:.3e} from {'its' if given else 'the nearest'} entity "
            f"({root[worst]}), more than the tolerance {tol[worst]:.3e} = tol_factor "
            f"{self.tol_factor:g} x facet size {h[worst]:.3e}"
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

    def _search_faces(self, fp: np.ndarray, gid: np.ndarray, tol: np.ndarray):
        """Global search: per facet the entity nearest to all its vertices.

        Candidates of a vertex: every entity whose bounding box holds it within
        its tolerance; each candidate is projected on (closed form, or Newton
        from the entity's own nearest search samples), results outside a
        trimmed face count as infinitely far.

        Returns:
            ``(root (nf,), params (nf, nfv, d), score (nf,))``, ``score`` the
            largest vertex distance to the chosen entity.
        """
        nf, nfv, _ = fp.shape
        d, ne = self.param_dim, self.num_entities
        flat = fp.reshape(-1, 3)
        vid = gid.reshape(-1)
        nv = int(vid.max()) + 1
        rep = np.unique(vid, return_index=True)[1]
        V = flat[rep]
        tv = np.zeros(nv)
        np.maximum.at(tv, vid, np.repeat(tol, nfv))
        pv, pe = _box_pairs(V, tv + 1e-12 * self.size, self.searcher.bbox_lo, self.searcher.bbox_hi)
        res = self.searcher.search_on(V[pv], pe, accept=self._accept)
        par, dist = res[0], res[2]
        if self._accept is not None:
            dist = np.where(res[3], dist, np.inf)
        near = np.zeros(nv, dtype=bool)
        near[pv[dist <= tv[pv]]] = True
        lost = np.flatnonzero(~near)
        if lost.size:  # off every candidate: the nearest entity anywhere (for the message)
            g = self.searcher.search(V[lost], accept=self._accept)
            gd = g[2] if self._accept is None else np.where(g[3], g[2], np.inf)
            pv, pe = np.concatenate([pv, lost]), np.concatenate([pe, g[0]])
            par, dist = np.concatenate([par, g[1]]), np.concatenate([dist, gd])
            k = pv * ne + pe
            o = np.lexsort((dist, k))  # the nearest result per (vertex, entity)
            o = o[np.concatenate([[True], k[o][1:] != k[o][:-1]])]
            pv, pe, par, dist = pv[o], pe[o], par[o], dist[o]
        key = pv * ne + pe
        order = np.argsort(key)
        key, par, dist, pv, pe = key[order], par[order], dist[order], pv[order], pe[order]
        # candidate (facet, entity): entities within tolerance of a facet vertex
        cnt_v = np.bincount(pv, minlength=nv)
        start_v = np.concatenate([[0], np.cumsum(cnt_v)])[:-1]
        cnt = cnt_v[vid]
        rows = np.repeat(start_v[vid], cnt) + _ramp(cnt)
        fac = np.repeat(np.repeat(np.arange(nf), nfv), cnt)
        near = dist[rows] <= tol[fac]
        # ... and each vertex's nearest entity (the facet's distance for the error message)
        best = best_per_group(pv, dist, nv)[vid]
        bf = np.repeat(np.arange(nf), nfv)[best >= 0]
        pair = np.unique(np.concatenate([fac[near] * ne + key[rows[near]] % ne,
                                         bf * ne + pe[best[best >= 0]]]))
        cf, ce = pair // ne, pair % ne  # every facet has one (its vertices' nearest entities)
        need = gid[cf].reshape(-1) * ne + np.repeat(ce, nfv)
        pos = np.minimum(np.searchsorted(key, need), len(key) - 1)
        dmax = np.where(key[pos] == need, dist[pos], np.inf).reshape(-1, nfv).max(axis=1)
        # choose per facet: smallest largest distance, ties to the lowest entity index
        order = np.lexsort((ce, dmax, cf))
        choice = order[np.searchsorted(cf[order], np.arange(nf))]
        params = par[pos].reshape(-1, nfv, d)[choice]
        return ce[choice].astype(np.int64), params, dmax[choice]

    def _on_faces(self, fp: np.ndarray, gid: np.ndarray, faces, seeds):
        """Parameters of every facet vertex on a given entity (known faces, optional seeds)."""
        nf, nfv, _ = fp.shape
        d = self.param_dim
        root = np.asarray(faces, dtype=np.int64).reshape(-1)
        if root.shape != (nf,):
            raise ValueError(f"faces must have shape ({nf},), got {root.shape}")
        if nf and (root.min() < 0 or root.max() >= self.num_entities):
            raise ValueError(f"faces refer to entities outside 0..{self.num_entities - 1}")
        X = fp.reshape(-1, 3)
        ent = np.repeat(root, nfv)
        tol = np.repeat(self.tol_factor * _edge_length(fp), nfv)
        sd = np.full((nf * nfv, d), np.nan) if seeds is None else \
            np.asarray(seeds, dtype=float).reshape(nf * nfv, d)
        # one projection per (vertex, entity): the slots of a vertex on one face share it
        key = gid.reshape(-1) * self.num_entities + ent
        _, first, inv = np.unique(key, return_index=True, return_inverse=True)
        inv = inv.reshape(-1)
        t = np.zeros(len(first))
        np.maximum.at(t, inv, tol)
        par = np.zeros((len(first), d))
        dist = np.full(len(first), np.inf)
        seeded = np.all(np.isfinite(sd[first]), axis=1) | self._analytic[ent[first]]
        if seeded.any():  # Newton from the given seeds (closed form on analytic faces)
            s = first[seeded]
            p, _, dd, _, conv = self.searcher.refine(s, ent[s], np.nan_to_num(sd[s]), X, self.max_iter)
            par[seeded], dist[seeded] = p, np.where(conv, dd, np.inf)
        todo = np.flatnonzero(~(dist <= t))
        if todo.size:  # the entity's own search samples
            s = first[todo]
            res = self.searcher.search_on(X[s], ent[s])
            better = res[2] < dist[todo]
            par[todo[better]], dist[todo[better]] = res[0][better], res[2][better]
        params = par[inv].reshape(nf, nfv, d)
        return root, params, dist[inv].reshape(nf, nfv).max(axis=1)

    def _edge_channels(self, keys: np.ndarray, allkeys: np.ndarray, nfv: int) -> np.ndarray:
        """CAD-edge channels ``(nf, 3, 3)`` from the facet-edge keys of all processes.

        ``keys (3 nf, 3)``: ``(node a, node b, face)`` of this process's facet
        edges; ``allkeys`` those of every process.  A facet edge is on a CAD
        edge if a facet sharing it (on any process) lies on another face.
        Channel ``m`` of facet vertex ``i`` is ``f_m (1 - delta_im)``.
        """
        nf = len(keys) // 3
        if nf == 0:
            return np.zeros((0, nfv, 3))
        row = _row_index(np.concatenate([keys[:, :2], allkeys[:, :2]]))
        n = int(row.max()) + 1
        lo = np.full(n, np.iinfo(np.int64).max)
        hi = np.full(n, np.iinfo(np.int64).min)
        np.minimum.at(lo, row[len(keys):], allkeys[:, 2])
        np.maximum.at(hi, row[len(keys):], allkeys[:, 2])
        mine = row[: len(keys)]
        flag = (lo[mine] != hi[mine]).reshape(nf, 3).astype(float)  # (nf, m)
        ch = np.repeat(flag[:, None, :], nfv, axis=1)  # (nf, i, m)
        ch[:, np.arange(nfv), np.arange(nfv)] = 0.0
        return ch

    # ------------------------------------------------------------------
    # hints from the mesher
    # ------------------------------------------------------------------
    def set_mesh_hints(self, facet_nodes: npt.ArrayLike, faces: npt.ArrayLike,
                       params: npt.ArrayLike | None = None) -> None:
        """Record where the mesh generator put the coarse boundary facets, for :meth:`attach`.

        Args:
            facet_nodes: ``(nf, nfv)`` global node ids of the boundary facets
                (as :meth:`attach` gets them, e.g. DOLFINx's input-global indices).
            faces: ``(nf,)`` entity (face in 3D, curve in 2D) of each facet.
            params: ``(nf, nfv, d)`` the vertices' parameters on those entities
                (Newton seeds; NaN where unknown).

        :meth:`attach` of facets with ``nodes`` then uses them (a facet is
        found by its set of node ids, on any process).  See
        :func:`nagata_snap.cad.meshed.use_cad_mesh`.
        """
        fn = np.asarray(facet_nodes, dtype=np.int64)
        nf = len(fn)
        faces = np.asarray(faces, dtype=np.int64).reshape(nf)
        d = self.param_dim
        par = np.full((nf, fn.shape[1], d), np.nan) if params is None else \
            np.asarray(params, dtype=float).reshape(nf, fn.shape[1], d)
        order = np.argsort(fn, axis=1)
        self._hints = {"nodes": np.take_along_axis(fn, order, axis=1), "faces": faces,
                       "params": np.take_along_axis(par, order[:, :, None], axis=1)}

    def _hinted(self, gid: np.ndarray):
        """``(faces (nf,), seeds (nf, nfv, d))`` from the mesh hints, or ``(None, None)``
        if some facet is not among them."""
        H = self._hints
        order = np.argsort(gid, axis=1)
        srt = np.take_along_axis(gid, order, axis=1)
        tbl = H["nodes"]
        row = _row_index(np.concatenate([tbl, srt]))
        where = np.full(int(row.max()) + 1, -1, dtype=np.int64)
        where[row[: len(tbl)]] = np.arange(len(tbl))
        hit = where[row[len(tbl):]]
        if np.any(hit < 0):
            return None, None
        rank = np.argsort(order, axis=1)  # position of each facet vertex among its sorted ids
        seeds = np.take_along_axis(H["params"][hit], rank[:, :, None], axis=1)
        return H["faces"][hit], seeds

    # ------------------------------------------------------------------
    # place / project: snap facet vertices
    # ------------------------------------------------------------------
    def place(
        self, records: Records, straight: npt.ArrayLike
    ) -> tuple[np.ndarray, Records, PlaceReport]:
        """Snap facet vertices onto their facets' entities (Kadir 2.2 + 2.3.3).

        Args:
            records: ``root (nf,)`` entity per facet and ``params (nf, nfv,
                record_width)`` seeds (old vertices: their parameters; new
                vertices: the parametric midpoint of the parent edge).
            straight: ``(nf, nfv, 3)`` current (straight) vertex positions.

        Returns:
            ``(points (nf, nfv, 3), records, report)``: projected positions
            (identical for every slot of the same vertex), records with the
            converged parameters (unwrapped relative to the seeds, hence
            contiguous within each facet), and a report with
            ``max_residual``/``mean_residual`` (snap distance over distinct
            vertices, length units), ``iterations_histogram`` (``np.bincount``
            of the Newton iterations of the seeded projections, one per
            distinct (vertex, entity, seed); analytic faces count 0),
            ``n_points`` (slots), ``n_vertices``, ``n_fallback`` (slots whose
            seeded projection failed or jumped farther than the facet's
            longest edge), ``n_off_root`` (positions taken from another
            entity: geometries without topology only), ``n_unresolved`` (no
            acceptable projection), ``n_left_face`` (seeded results outside
            their face's loops; without topology they fall back to other
            entities, with topology they go to the face's boundary),
            ``n_edge_vertices`` (vertices put on CAD edges or corners) and
            ``max_edge_gap`` (largest distance of such a vertex from one of
            its faces).

        Fallbacks, in order: the other vertices' parameters of the facet and
        their mean as seeds; the entity's own search samples.  Without
        topology also: entities whose bounding box is within an edge length,
        and a global search.
        """
        st, root, params, chan = self._unpack(records, straight, "straight")
        nf, nfv, _ = st.shape
        d = self.param_dim
        ns = nf * nfv
        if ns == 0:
            return np.zeros((nf, nfv, 3)), Records(root.copy(), np.asarray(records.params).copy()), PlaceReport()
        X = st.reshape(ns, 3)
        ent = np.repeat(root, nfv)
        seed = params.reshape(ns, d)
        hs = np.repeat(_edge_length(st), nfv)
        par, proj, dist, its, valid, info = self._on_root(ent, X, seed, params, hs)
        on_root = np.ones(ns, dtype=bool)
        if self.topology is None:
            info["n_left_face"] = 0
            if self._accept is not None:  # a result beyond the face's trimming loops: fall back
                left = valid & ~self._accept(ent, par)
                info["n_left_face"] = int(left.sum())
                valid &= ~left
            self._other_entities(ent, X, hs, par, proj, dist, valid, on_root)
        else:
            info["n_left_face"] = 0
        n_unresolved = int(np.sum(~valid))
        par = self._unwrap_result(root, ent, par, seed)
        proj, par, dist, gid, rep_of_group, n_edge, gap, n_left = self._merge(
            ent, X, proj, par, seed, dist, valid, on_root, hs, chan.reshape(ns, -1))
        if self.topology is not None:
            info["n_left_face"] = n_left
        vd = dist[rep_of_group]  # one value per distinct vertex
        report = PlaceReport(
            max_residual=float(vd.max()) if vd.size else 0.0,
            mean_residual=float(vd.mean()) if vd.size else 0.0,
            iterations_histogram=np.bincount(its, minlength=1),
            n_points=int(ns),
            n_vertices=int(vd.size),
            n_fallback=int(info["n_fallback"]),
            n_off_root=int(np.sum(~on_root)),
            n_unresolved=n_unresolved,
            n_left_face=int(info["n_left_face"]),
            n_edge_vertices=int(n_edge),
            max_edge_gap=float(gap),
        )
        out = np.concatenate([par.reshape(nf, nfv, d), chan], axis=2) if chan.shape[2] else \
            par.reshape(nf, nfv, d)
        return proj.reshape(nf, nfv, 3), Records(root.copy(), out), report

    def project(self, records: Records, points: npt.ArrayLike) -> tuple[np.ndarray, Records]:
        """Closest points of ``points`` on each facet's own entity (no other entity).

        Seeded by ``records.params``; a vertex on a CAD edge (its record's
        edge channels) goes to the closest point of that edge, a corner (see
        the module docstring: decided from all facets of the vertex) stays at
        its CAD vertex, so it stays on its feature.  Used to slide boundary
        vertices tangentially.

        Args:
            records: records of ``nf`` facets.
            points: ``(nf, nfv, 3)`` target positions (one per mesh vertex:
                slots of a vertex should carry the same point).

        Returns:
            ``(points (nf, nfv, 3), records)``: positions on the geometry and
            the records with the new parameters.
        """
        pts, root, params, chan = self._unpack(records, points, "points")
        nf, nfv, _ = pts.shape
        d = self.param_dim
        ns = nf * nfv
        if ns == 0:
            return np.zeros((nf, nfv, 3)), Records(root.copy(), np.asarray(records.params).copy())
        X = pts.reshape(ns, 3)
        ent = np.repeat(root, nfv)
        seed = params.reshape(ns, d)
        hs = np.repeat(_edge_length(pts), nfv)
        par, proj, dist, _, valid, _ = self._on_root(ent, X, seed, params, hs, jump=False)
        par = self._unwrap_result(root, ent, par, seed)
        proj, par, *_ = self._merge(ent, X, proj, par, seed, dist, valid,
                                    np.ones(ns, dtype=bool), hs, chan.reshape(ns, -1))
        out = np.concatenate([par.reshape(nf, nfv, d), chan], axis=2) if chan.shape[2] else \
            par.reshape(nf, nfv, d)
        return proj.reshape(nf, nfv, 3), Records(root.copy(), out)

    def _on_root(self, ent, X, seed, params, hs, jump: bool = True):
        """Projection of every slot onto its facet's entity, with fallbacks on that entity.

        Seeded Newton (closed form on analytic entities); where it fails (or,
        with ``jump``, lands farther than the facet's longest edge): the
        facet's other vertices' parameters and their mean as seeds, then the
        entity's own search samples.

        Returns:
            ``(params, points, dist, iterations, valid, info)``.
        """
        nf, nfv, d = params.shape
        ns = len(ent)
        par, proj, dist, its, conv = self._project(ent, X, seed)
        ok = conv & np.all(np.isfinite(proj), axis=1)
        if jump:
            ok &= dist <= hs
        dist = np.where(np.isfinite(dist), dist, np.finfo(float).max)
        bad = np.flatnonzero(~ok)
        info = {"n_fallback": int(bad.size)}
        if bad.size:
            # other seeds: the facet's other vertices' params and their mean
            f = bad // nfv
            cand = np.concatenate([params[f], params[f].mean(axis=1, keepdims=True)], axis=1)
            m = nfv + 1
            pt = np.repeat(bad, m)
            cp, cx, cd, _, cc = self.searcher.refine(pt, ent[pt], cand.reshape(-1, d), X, self.max_iter)
            good = cc & (cd <= hs[pt] if jump else np.isfinite(cd))
            rows = best_per_group(np.repeat(np.arange(bad.size), m), cd, bad.size, good)
            hit = rows >= 0
            s, r = bad[hit], rows[hit]
            par[s], proj[s], dist[s], ok[s] = cp[r], cx[r], cd[r], True
            bad = np.flatnonzero(~ok)
        if bad.size:
            # the entity's own search samples
            res = self.searcher.search_on(X[bad], ent[bad])
            good = (res[2] <= hs[bad]) if jump else np.isfinite(res[2])
            closer = good | (res[2] < dist[bad])
            s = bad[closer]
            par[s], proj[s], dist[s] = res[0][closer], res[1][closer], res[2][closer]
            ok[bad[good]] = True
        return par, proj, dist, its, ok, info

    def _other_entities(self, ent, X, hs, par, proj, dist, valid, on_root) -> None:
        """Geometries without topology: slots still invalid try nearby entities, then all.

        Updates the arrays in place; a position from another entity clears
        ``on_root`` (the slot keeps its best parameters on its own entity).
        """
        acc = self._accept
        bad = np.flatnonzero(~valid)
        if bad.size:
            # KD-tree seeds on the root entity and on entities whose bbox is near
            lo, hi = self.searcher.bbox_lo, self.searcher.bbox_hi
            pb, be = _box_pairs(X[bad], hs[bad], lo, hi)
            bi = np.concatenate([pb, np.arange(bad.size)])
            be = np.concatenate([be, ent[bad]])
            u = np.unique(bi * self.num_entities + be)
            bi, be = u // self.num_entities, u % self.num_entities
            res = self.searcher.search_on(X[bad][bi], be, accept=acc)
            qp, qx, qd = res[:3]
            qroot = be == ent[bad][bi]
            qok = qd <= hs[bad][bi]
            if acc is not None:  # only results on the faces (neighbours sharing the edge)
                qok &= res[3]
            r_root = best_per_group(bi, qd, bad.size, qroot)  # best attempt on the root
            r_ok = best_per_group(bi, qd, bad.size, qok & qroot)  # acceptable on the root
            r_any = best_per_group(bi, qd, bad.size, qok)  # acceptable anywhere
            use_root = r_ok >= 0
            use_other = ~use_root & (r_any >= 0)
            s, r = bad[use_root], r_ok[use_root]
            par[s], proj[s], dist[s], valid[s] = qp[r], qx[r], qd[r], True
            s, r = bad[use_other], r_any[use_other]
            proj[s], dist[s], valid[s], on_root[s] = qx[r], qd[r], True, False
            upd = ~use_root & (r_root >= 0)
            s, r = bad[upd], r_root[upd]
            closer = ~valid[s] & (qd[r] < dist[s])
            par[s] = np.where((~valid[s] | ~on_root[s])[:, None], qp[r], par[s])
            proj[s[closer]], dist[s[closer]] = qx[r[closer]], qd[r[closer]]
            bad = np.flatnonzero(~valid)
        if bad.size:
            # global search over all entities
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

    def _unwrap_result(self, root, ent, par, seed) -> np.ndarray:
        """Unwrap results relative to the seeds (contiguous within the facet); facets
        with non-finite seeds relative to their first vertex."""
        nf = len(root)
        d = self.param_dim
        nfv = len(ent) // max(nf, 1)
        par = self._unwrap(ent, par, seed)
        nanf = ~np.all(np.isfinite(seed).reshape(nf, -1), axis=1)
        if nanf.any():
            pf = par.reshape(nf, nfv, d)
            sub = pf[nanf]
            ref = np.repeat(sub[:, :1], nfv, axis=1).reshape(-1, d)
            pf[nanf] = self._unwrap(np.repeat(root[nanf], nfv), sub.reshape(-1, d), ref).reshape(-1, nfv, d)
            par = pf.reshape(-1, d)
        return par

    def _merge(self, ent, X, proj, par, seed, dist, valid, on_root, hs, chan):
        """One position per mesh vertex; CAD edges and corners; parameters of every slot.

        Every slot of a vertex gets the position of its best slot (an edge or
        corner slot first, then valid, on its own entity, nearest).  With
        topology, a vertex on a CAD edge (corner) is taken to the nearest edge
        curve (CAD vertex) of its face and from there onto the intersection of
        the faces of that edge (vertex): the edge curves of a file are only
        within their tolerance of the faces.  Every slot then takes the
        parameters of the final position on its own entity.

        A face slot of a trimmed face whose projection lies outside the face's
        loops is treated as an edge slot: the parametric midpoints of a
        facet's vertices can leave a face where its boundary is concave, and
        the nearest point of the face is then on its boundary.

        Returns ``(proj, par, dist, gid, rep_of_group, n_edge, max_edge_gap,
        n_left)``, ``n_left`` the slots found outside their face's loops.
        """
        ns = len(ent)
        gid = _groups(X, MERGE_RTOL * self.size)
        cls = np.zeros(ns, dtype=np.int64)
        fid = np.zeros(ns, dtype=np.int64)
        n_edge, gap = 0, 0.0
        n_left = 0
        if self.topology is not None and chan.shape[1]:
            cls = np.count_nonzero(chan == 1.0, axis=1)  # 0 face, 1 edge, >= 2 corner
            if self.trims is not None:
                # a face slot outside its face's loops (the surface's extension beyond a
                # curved face boundary: parametric midpoints in a concave part of the face)
                # goes to the nearest point of the face's boundary
                fs = np.flatnonzero((cls == 0) & self.trims.trimmed[ent])
                off = fs[~self.trims.inside(ent[fs], par[fs])]
                cls[off] = 1
                n_left = int(off.size)
            feat = np.flatnonzero(cls > 0)
            if feat.size:
                fx, ff = self._features(ent[feat], X[feat], hs[feat], cls[feat])
                ok = ff != 0
                proj[feat[ok]] = fx[ok]
                fid[feat] = ff
                cls[feat[~ok]] = 0
            # corners not yet at a CAD vertex (decided from all slots of the vertex, not per
            # facet; X may be a target off the vertex), and edge slots whose record is at a
            # CAD vertex (a seam's end on a closed edge): the CAD vertex where the record is
            corner = np.flatnonzero((self._corner_groups(gid, ent, fid)[gid] | (cls >= 1)) & (fid >= 0)
                                    & np.all(np.isfinite(seed), axis=1))
            if corner.size:
                at = self.evaluate(ent[corner], seed[corner][:, None]).reshape(-1, 3)
                fx, ff = self._features(ent[corner], at, hs[corner], np.full(corner.size, 2))
                hit = ff < 0
                c = corner[hit]
                proj[c], fid[c], cls[c] = fx[hit], ff[hit], 2
        order = np.lexsort((dist, ~on_root, ~valid, -np.minimum(cls, 2), gid))
        g_sorted = gid[order]
        first = np.ones(ns, dtype=bool)
        first[1:] = g_sorted[1:] != g_sorted[:-1]
        rep_of_group = np.empty(int(gid.max()) + 1, dtype=np.int64)
        rep_of_group[g_sorted[first]] = order[first]
        rep = rep_of_group[gid]
        feat_slot = cls[rep] > 0
        if feat_slot.any():  # onto the intersection of the feature's faces
            gap = self._onto_feature(rep_of_group, gid, ent, proj, par, fid, hs)
            n_edge = int(np.unique(gid[feat_slot]).size)
        moved = np.linalg.norm(proj - proj[rep], axis=1) > 1e-9 * self.size
        redo = (feat_slot | moved) & (ent == ent[rep]) if self.topology is None else (feat_slot | moved)
        proj = proj[rep]
        if redo.any():  # the slot's parameters of the representative position, on its own entity
            idx = np.flatnonzero(redo)
            p, _, dd, _, _ = self._project(ent[idx], proj[idx], par[idx])
            far = np.flatnonzero(~(dd <= 1e-9 * self.size))
            if far.size:  # the seed led Newton astray (e.g. across a seam): the face's own samples
                res = self.searcher.search_on(proj[idx[far]], ent[idx[far]])
                better = res[2] < dd[far]
                p[far[better]], dd[far[better]] = res[0][better], res[2][better]
            par[idx] = self._unwrap(ent[idx], p, seed[idx])
            if feat_slot.any():
                gap = max(gap, float(dd[feat_slot[redo]].max(initial=0.0)))
        if self.topology is None:
            n_edge, gap = self._edge_vertices(gid, ent, proj, par, seed, X, hs)
        dist = np.linalg.norm(proj - X, axis=1)
        return proj, par, dist, gid, rep_of_group, n_edge, gap, n_left

    def _corner_groups(self, gid: np.ndarray, ent: np.ndarray, fid: np.ndarray) -> np.ndarray:
        """``(n_groups,)`` mask of the vertices that are CAD corners.

        The rule of :func:`nagata_snap.mesh.corners.corner_vertices`: a vertex
        (group ``gid`` of its slots) is a corner if its slots lie on three or
        more distinct faces (``ent``) or on two or more distinct CAD edges
        (``fid > 0``: edge curve ``fid - 1``, see :meth:`_features`), whatever
        each facet's own edge channels say.
        """
        return corner_vertices(gid, ent, int(gid.max()) + 1, self.param_dim + 1, edge=np.where(fid > 0, fid - 1, -1))

    def _onto_feature(self, rep_of_group, gid, ent, proj, par, fid, hs) -> float:
        """Move feature vertices onto the intersection of their edge's (vertex's) faces.

        ``fid``: per slot ``c + 1`` for edge curve ``c``, ``-(v + 1)`` for CAD
        vertex ``v``.  Updates ``proj`` of the representative slots in place;
        returns the largest remaining distance to one of the faces.
        """
        top = self.topology
        reps = rep_of_group[np.unique(gid)]
        reps = reps[fid[reps] != 0]
        f = fid[reps]
        rows = np.where(f > 0, f - 1, len(top.curves) - f - 1)  # see _Topology.feature_faces
        multi = top.feature_faces.counts[rows] > 1  # on the intersection of several faces
        reps, rows = reps[multi], rows[multi]
        if reps.size == 0:
            return 0.0
        cnt, pe = top.feature_faces.take(rows)
        gpos = np.repeat(np.arange(reps.size), cnt)
        # seeds: the representative's own parameters on its own face
        seeds = np.full((len(pe), self.param_dim), np.nan)
        own = pe == ent[reps][gpos]
        seeds[own] = par[reps][gpos[own]]
        x, _, g = self._intersect(proj[reps], gpos, pe, seeds, hs[reps], proj[reps])
        proj[reps] = x
        return float(g.max(initial=0.0))

    def _intersect(self, x0, gpos, pe, seeds, hg, anchor):
        """Gauss-Newton onto the intersection of several entities per point.

        Points ``x0 (G, 3)``; pairs ``(gpos (m,), pe (m,))`` (point, entity),
        sorted by point, with Newton seeds ``(m, d)`` (NaN: from the entity's
        search samples).  Each step projects ``x`` onto every entity of the
        point and moves it to the nearest point of the intersection of the
        tangent planes there (``n_i . (y - p_i) = 0``, minimum-norm least
        squares, step capped to ``hg``).  Directions in which the normals are
        (nearly) dependent -- faces meeting tangentially, as a fillet or a
        chamfer cone meets its plane -- get no step (:func:`_truncated_lstsq`):
        along a tangent contact the intersection is ill-posed and the start
        (the edge curve's point) is kept there.  The best point over :data:`EDGE_SWEEPS` steps is
        kept if it is nearer all the entities than the start and within ``hg``
        of ``anchor``.

        Returns ``(x (G, 3), params (m, d), gap (G,))``: ``gap`` the largest
        distance of the final point to one of its entities.
        """
        G, m = len(x0), len(gpos)
        start = np.searchsorted(gpos, np.arange(G))
        rank = np.arange(m) - start[gpos]
        etol = EDGE_RTOL * self.size

        def distances(x, sd):
            pp, px, pd = np.zeros((m, self.param_dim)), np.zeros((m, 3)), np.zeros(m)
            known = np.all(np.isfinite(sd), axis=1)
            if known.any():
                k = np.flatnonzero(known)
                pp[k], px[k], pd[k], _, _ = self.searcher.refine(gpos[k], pe[k], sd[k], x, self.max_iter)
            if not known.all():
                k = np.flatnonzero(~known)
                pp[k], px[k], pd[k] = self.searcher.search_on(x[gpos[k]], pe[k])
            score = np.zeros(G)
            np.maximum.at(score, gpos, pd)
            return pp, px, score

        x = x0.copy()
        pp, px, score = distances(x, seeds)
        pp0, score0 = pp.copy(), score.copy()
        best_x, best_pp, best = x.copy(), pp.copy(), score.copy()
        todo = best > etol
        mr = int(rank.max()) + 1
        for _sweep in range(EDGE_SWEEPS):
            if not todo.any():
                break
            nrm = self._normals(pe, pp)  # (m, 3), zero where degenerate (pole)
            N = np.zeros((G, mr, 3))
            N[gpos, rank] = nrm
            res = np.zeros((G, mr))
            res[gpos, rank] = np.einsum("ij,ij->i", nrm, x[gpos] - px)
            step = _truncated_lstsq(N, res)
            sl_ = np.linalg.norm(step, axis=1)
            step *= np.minimum(1.0, hg / np.maximum(sl_, 1e-300))[:, None]
            x = np.where(todo[:, None], x - step, x)
            pp, px, score = distances(x, pp)
            better = todo & (score < best)
            best_x[better], best[better] = x[better], score[better]
            best_pp[better[gpos]] = pp[better[gpos]]
            todo &= best > etol
        keep = (best < score0) & (np.linalg.norm(best_x - anchor, axis=1) <= hg)
        x_fin = np.where(keep[:, None], best_x, x0)
        pp_fin = np.where(keep[gpos][:, None], best_pp, pp0)
        return x_fin, pp_fin, np.where(keep, best, score0)

    def _features(self, ent, X, hs, cls):
        """Positions of edge and corner slots: nearest edge curve / CAD vertex of their face.

        Returns ``(points (k, 3), feature (k,))``: ``c + 1`` for edge curve
        ``c``, ``-(v + 1)`` for CAD vertex ``v``, 0 where none was found.
        """
        top = self.topology
        k = len(ent)
        out = np.zeros((k, 3))
        fid = np.zeros(k, dtype=np.int64)
        # corners: the nearest CAD vertex of the face within the facet's tolerance
        corner = np.flatnonzero(cls >= 2)
        if corner.size:
            cnt, vert = top.face_vertices.take(ent[corner])
            slot = np.repeat(corner, cnt)
            dv = np.linalg.norm(top.points[vert] - X[slot], axis=1)
            best = best_per_group(np.repeat(np.arange(corner.size), cnt), dv, corner.size,
                                  dv <= self.tol_factor * hs[slot])
            hit = best >= 0
            out[corner[hit]] = top.points[vert[best[hit]]]
            fid[corner[hit]] = -(vert[best[hit]] + 1)
        # edges (and corners without a vertex nearby): the nearest edge curve of the face
        todo = np.flatnonzero(fid == 0)
        if todo.size and top.searcher is not None:
            cnt, crv = top.face_curves.take(ent[todo])
            slot = np.repeat(todo, cnt)
            t = hs[slot][:, None]
            inbox = np.all((X[slot] >= top.lo[crv] - t) & (X[slot] <= top.hi[crv] + t), axis=1)
            slot, crv = slot[inbox], crv[inbox]
            grp = np.searchsorted(todo, slot)
            res = top.searcher.search_on(X[slot], crv)
            best = best_per_group(grp, res[2], todo.size, res[2] <= hs[slot])
            hit = best >= 0
            out[todo[hit]] = res[1][best[hit]]
            fid[todo[hit]] = crv[best[hit]] + 1
        return out, fid

    def _normals(self, ent: np.ndarray, params: np.ndarray) -> np.ndarray:
        """Unit ``S_u x S_v`` (zero where degenerate) of surfaces; curves: zero."""
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
            ok = n > (DEGENERATE_RTOL * ent_e.bbox_size) ** 2 / np.maximum(lengths[0] * lengths[1], 1e-300)
            out[sel[ok]] = c[ok] / n[ok, None]
        return out

    def vertex_normals(self, records: Records) -> np.ndarray:
        """Unit surface normals of every facet vertex on its facet's entity, ``(nf, nfv, 3)``.

        3D: the normal of the facet's face at the vertex's ``(u, v)``, exact
        from the surface (analytic formulas, also at poles; NURBS:
        ``S_u x S_v``, at degenerate points taken a step ``1e-6`` of the way
        towards the facet's parametric centre), pointing out of the solid
        when the geometry has the model's face orientations (else along
        ``S_u x S_v``: orientation free).  2D: the in-plane normal of the
        curve, ``(t_y, -t_x, 0)`` for the unit tangent ``t`` (outward for a
        profile's edges when their orientation in the face is known).
        """
        root = np.asarray(records.root, dtype=np.int64).reshape(-1)
        params = np.asarray(records.params, dtype=float)
        nf, nfv = params.shape[:2]
        d = self.param_dim
        P = params[:, :, :d].reshape(-1, d)
        ent = np.repeat(root, nfv)
        out = np.zeros((nf * nfv, 3))
        sign = self._orientation()[ent]
        if d == 1:
            for e in np.unique(ent):  # loop over entities
                sel = np.flatnonzero(ent == e)
                c = self.entities[e]
                _, T = evaluate_params(c, normalize_params(c, P[sel]), 1)
                t = T[:, 0] / np.maximum(np.linalg.norm(T[:, 0], axis=1, keepdims=True), 1e-300)
                out[sel] = np.stack([t[:, 1], -t[:, 0], np.zeros(len(sel))], axis=1)
            return (out * sign[:, None]).reshape(nf, nfv, 3)
        centre = np.repeat(params[:, :, :d].mean(axis=1), nfv, axis=0)
        for e in np.unique(ent):  # loop over entities
            sel = np.flatnonzero(ent == e)
            s = self.entities[e]
            if hasattr(s, "normals"):
                out[sel] = s.normals(P[sel])
                continue
            n = self._normals(ent[sel], P[sel])
            bad = np.linalg.norm(n, axis=1) == 0
            if bad.any():
                nudge = P[sel][bad] + NORMAL_NUDGE * (centre[sel][bad] - P[sel][bad])
                n[bad] = self._normals(ent[sel][bad], nudge)
            out[sel] = n
        return (out * sign[:, None]).reshape(nf, nfv, 3)

    def _orientation(self) -> np.ndarray:
        """``(num_entities,)`` +1/-1: outward sign of each entity's normal (+1 if unknown).

        3D: -1 for faces used reversed in the shape.  2D: a wire keeps its
        face on its left (seen from the face's oriented normal), so the
        outward in-plane normal of an edge is ``tau x n_face``, ``tau`` the
        tangent in the wire's sense: the sign of the wire's sense along the
        curve times the face normal's ``z``.
        """
        sign = np.ones(self.num_entities)
        if self.model is None:
            return sign
        if self.param_dim == 2:
            return np.array([-1.0 if f.reversed else 1.0 for f in self.model.faces])
        pos = np.full(len(self.model.edges), -1, dtype=np.int64)
        pos[self._curve_edges] = np.arange(len(self._curve_edges))
        for f in self.model.faces:
            up = np.sign(np.cross(f.surface.X, f.surface.Y)[2]) * (-1.0 if f.reversed else 1.0)
            for lp in f.loops:
                e = pos[lp.edges]
                sign[e[e >= 0]] = lp.senses[e >= 0] * (up if up != 0 else 1.0)
        return sign

    def _edge_vertices(
        self, gid: np.ndarray, ent: np.ndarray, proj: np.ndarray, par: np.ndarray,
        seed: np.ndarray, X: np.ndarray, hs: np.ndarray,
    ) -> tuple[int, float]:
        """Geometries without topology: put vertices shared by facets of several entities
        onto all of them.

        A mesh vertex on facets of entities ``A`` and ``B`` lies on the CAD edge
        the two faces share.  Gauss-Newton steps converge to the edge: project
        ``x`` onto every entity of the vertex (seeded Newton), move ``x`` to the
        nearest point of the intersection of the tangent planes there
        (``n_i . (y - p_i) = 0``, least squares, step capped to the local edge
        length), repeat.  The best point over :data:`EDGE_SWEEPS` steps is used
        if it is nearer all the entities than the start and within the local
        edge length of the straight vertex.  Every slot then takes the
        parameters of that point on its own entity.  Only the facets on this
        process are seen: geometries with topology use the CAD edges instead.

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
        gslot = first_slot[pidx][start]  # one slot per edge vertex
        x = proj[gslot].copy()
        hg = np.zeros(G)
        sl = np.flatnonzero(np.isin(gid, groups))
        np.maximum.at(hg, np.searchsorted(groups, gid[sl]), hs[sl])
        x_fin, pp_fin, gap = self._intersect(x, gpos, pe, par[first_slot[pidx]], hg, X[gslot])
        pos = np.full(len(ukey), -1, dtype=np.int64)
        pos[pidx] = np.arange(m)
        ps = pos[inv]
        s = np.flatnonzero(ps >= 0)
        proj[s] = x_fin[gpos[ps[s]]]
        par[s] = self._unwrap(ent[s], pp_fin[ps[s]], par[s])
        return int(G), float(gap.max())
