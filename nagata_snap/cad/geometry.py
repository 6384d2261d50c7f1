"""CadGeometry: snap boundary vertices onto the faces, edges and vertices of a CAD model.

:class:`CadGeometry` is the snapping geometry of Kadir (2010), chapter 2, on
the B-rep of a CAD file (:meth:`CadGeometry.from_file`: STEP, IGES or BREP
through OpenCASCADE) or on bare NURBS entities.  This module holds the
construction and the queries; the stages live in their own modules:

* :mod:`~nagata_snap.cad.attach`: :meth:`CadGeometry.attach` initialises the
  coarse mesh (Kadir 2.3.1): each boundary facet gets ONE entity (face in
  3D, edge curve in 2D) on which all its vertices lie (Kadir 2.3.4) and the
  parameters of its vertices there (the ``(n, u)`` / ``(n, u, v)`` tuples
  of Kadir 2.3.2), stored per facet in
  :class:`nagata_snap.mesh.records.Records`.  The entity is known when the
  mesh came from the CAD (``faces``, or the gmsh classification recorded
  with :meth:`CadGeometry.set_mesh_hints`); otherwise a global search finds
  it (trimmed faces only count within their loops,
  :class:`~nagata_snap.cad.trimming.TrimLoops`).
* :mod:`~nagata_snap.cad.place`: :meth:`CadGeometry.place` snaps after a
  refinement (Kadir 2.2, Algorithm 1, neighbour seeds of 2.3.3): each vertex
  is projected onto its facet's entity, seeded with the record's parameters
  (for a new vertex the parametric midpoint of its parent edge; seam-aware,
  :mod:`~nagata_snap.cad.params`).
* :mod:`~nagata_snap.cad.features`: CAD edges and corners.

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
curves (:func:`nagata_snap.mesh.corners.corner_vertices`), or if it is on a
flagged edge and its record puts it at a CAD vertex (the mesher's node
there, e.g. the end of a seam on a closed edge); one rule for :meth:`place`
and :meth:`project` (:func:`nagata_snap.cad.place.merge`), so a corner
never moves along one of its edges.  Every facet then takes the ``(u, v)``
of that point on its own face.  All processes that hold a facet of the
vertex compute the same point, so sharp edges stay sharp after any number
of levels and in parallel.  Geometries built from bare entities (no
topology) fall back to putting a vertex shared by facets of several
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
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, overload

import numpy as np
import numpy.typing as npt

from nagata_snap.cad import attach as _attach
from nagata_snap.cad import place as _place
from nagata_snap.cad.attach import MeshHints
from nagata_snap.cad.boundary import with_boundary
from nagata_snap.cad.errors import CadError
from nagata_snap.cad.params import unit_normals
from nagata_snap.cad.projection import (
    GlobalSearcher,
    _points3,
    entity_periods,
    evaluate_params,
    is_analytic,
    normalize_params,
)
from nagata_snap.cad.stage import CadTopology
from nagata_snap.cad.trimming import TRIM_RTOL, TrimLoops
from nagata_snap.geometry import PlaceReport
from nagata_snap.mesh.arrays import Groups, best_per_group
from nagata_snap.mesh.records import Records

if TYPE_CHECKING:
    from nagata_snap.cad.topology import CadModel

__all__ = ["CadError", "CadGeometry", "TrimLoops"]

#: step of the parameter nudge that gives normals at degenerate points (poles,
#: apexes), as a fraction of the way to the facet's parametric centre
NORMAL_NUDGE = 1e-6


class _PerEntity(Sequence[np.ndarray | None]):
    """``f(i)`` for ``i < n`` as a read-only sequence, evaluated when indexed (lazy per-entity data)."""

    def __init__(self, n: int, f: Callable[[int], np.ndarray | None]):
        self._n, self._f = n, f

    def __len__(self) -> int:
        return self._n

    @overload
    def __getitem__(self, i: int) -> np.ndarray | None: ...

    @overload
    def __getitem__(self, i: slice) -> list[np.ndarray | None]: ...

    def __getitem__(self, i: int | slice) -> np.ndarray | list[np.ndarray | None] | None:
        if isinstance(i, slice):
            return [self._f(k) for k in range(self._n)[i]]
        if not -self._n <= i < self._n:
            raise IndexError(f"entity {i} of {self._n}")
        return self._f(i % self._n)


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
        entities: Sequence[Any],
        trim_loops: Sequence[np.ndarray | None] | None = None,
        trim_holes: Sequence[Sequence[np.ndarray] | None] | None = None,
        *,
        tol_factor: float = 1e-2,
        k_seeds: int = 6,
        max_iter: int = 20,
        per_span: int | None = None,
        trim_rtol: float = TRIM_RTOL,
        model: CadModel | None = None,
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
        self.trims = trims = self._trims(trim_loops, trim_holes, trim_rtol)
        extra = None if trims is None else _PerEntity(len(entities), trims.loop_points)
        filt = None if trims is None else (  # search samples inside the loops only
            lambda e, P: trims.inside(np.full(len(P), e), P, band=False))
        self.searcher = GlobalSearcher(entities, per_span=per_span, k_seeds=k_seeds,
                                       sample_filter=filt, extra_samples=extra)
        self.size = self.searcher.size
        #: ``(n_entities, d)`` period of each parameter direction (NaN where open), as the trims have them
        self._period = trims._period if trims is not None else np.array([entity_periods(e) for e in entities])
        #: ``(n_entities,)`` bool: closed-form projection (no seeds needed)
        self._analytic = np.array([is_analytic(e) for e in entities], dtype=bool)
        #: ``(n_entities,)`` bounding-box diagonal of each entity (length units)
        self._sizes = np.linalg.norm(self.searcher.bbox_hi - self.searcher.bbox_lo, axis=1)
        self.topology = CadTopology(model) if model is not None and self.param_dim == 2 else None
        #: channels per facet vertex in the records: the parameters, plus in 3D with
        #: topology the three CAD-edge channels
        self.record_width = self.param_dim + (3 if self.topology is not None else 0)
        self._hints: MeshHints | None = None
        #: 2D geometries of a model: the model edge of each entity
        self._curve_edges: np.ndarray | None = None

    def _trims(self, trim_loops: Sequence[np.ndarray | None] | None,
               trim_holes: Sequence[Sequence[np.ndarray] | None] | None, rtol: float) -> TrimLoops | None:
        n = len(self.entities)
        for name, arr in (("trim_loops", trim_loops), ("trim_holes", trim_holes)):
            if arr is not None and len(arr) != n:
                raise ValueError(f"{name} has {len(arr)} entries for {n} entities")
        if self.model is not None and self.param_dim == 2:
            return self.model.trim_loops(rtol)
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
    def from_model(cls, model: CadModel, *, dim: int | None = None, **kwargs: Any) -> CadGeometry:
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
        comm: Any = None,
        **kwargs: Any,
    ) -> CadGeometry:
        """Geometry of a STEP (``.step/.stp``), IGES (``.igs/.iges``) or BREP file.

        The file is read by OpenCASCADE (:mod:`nagata_snap.cad.read`):
        faces that share no edge, as in most IGES files, sewn into shells
        and solids (joined on the read data where they meet cleanly,
        :mod:`nagata_snap.cad.sewing`, else by OpenCASCADE's sewing and
        ``ShapeFix_Shape``), analytic faces kept analytic, every other face
        converted to NURBS, trimming loops from the p-curves.

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
        from nagata_snap.cad.worker import collector_paused

        with collector_paused():
            return cls._from_file(path, dim, unit, heal, isolate, timeout, comm, **kwargs)

    @classmethod
    def _from_file(cls, path: str | os.PathLike, dim: int | None, unit: str, heal: bool, isolate: bool,
                   timeout: float | None, comm: Any, **kwargs: Any) -> CadGeometry:
        """:meth:`from_file`'s work."""
        from nagata_snap.cad.topology import CadModel
        from nagata_snap.cad.verify import read_verified

        data: dict | None = None
        model: CadModel | None = None
        err: str | None = None
        if comm is None or comm.rank == 0:
            try:
                data, model = read_verified(path, unit=unit, heal=heal, isolate=isolate, timeout=timeout)
            except CadError as e:
                err = str(e)
        if comm is not None:
            data, err = comm.bcast((data, err), root=0)
        if err is not None:
            raise CadError(err)
        assert data is not None  # read_cad returns the model's data or raises
        try:
            if model is None:  # (the other ranks: the model of rank 0's verified data)
                model = CadModel.from_data(data)
            return cls.from_model(model, dim=dim, **kwargs)
        except ValueError as e:  # geometry OpenCASCADE accepted but that cannot be used
            msg = str(e)
            raise CadError(msg if os.fspath(path) in msg or data["path"] in msg
                           else f"{data['path']}: {msg}") from None

    @classmethod
    def from_iges(cls, path: str | os.PathLike, *, dim: int | None = None, unit: str = "FILE",
                  **kwargs: Any) -> CadGeometry:
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
    def _accept(self) -> Callable[[np.ndarray, np.ndarray], np.ndarray] | None:
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
        g = Groups(root)
        P = params[g.order][:, :, :d]
        out = np.empty((nf, nfv, 3))
        for e, sl in g:  # loop over entities
            p = normalize_params(self.entities[e], P[sl].reshape(-1, d))
            out[sl] = evaluate_params(self.entities[e], p, 0).reshape(-1, nfv, 3)
        return g.unsort(out)

    def closest_point(self, points: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest point of each point on the (trimmed) faces: global search.

        Newton from the ``k_seeds`` nearest grid samples (samples on the faces
        only; analytic faces in closed form); a result on a surface's
        extension beyond its face's trimming loops does not count.  With a
        model's topology, a face whose surface foot point is outside it (or
        within the band of a loop and outside the trimming curve) competes
        with its boundary's closest point, on its edge curves
        (:mod:`~nagata_snap.cad.boundary`).

        Returns:
            ``(entity (n,) int64, params (n, d), distance (n,))``; entity ``-1``
            and distance ``inf`` where no seed converged onto a face.
        """
        X = np.asarray(points, dtype=float)
        if self.trims is None or self.topology is None or self.topology.searcher is None:
            res = self.searcher.search(X, accept=self._accept)
            ent, par, dist = res[:3]
            if self.trims is not None:
                ok = res[3]
                ent = np.where(ok, ent, -1)
                dist = np.where(ok, dist, np.inf)
            return ent.astype(np.int64), par, dist
        X = _points3(X)
        if len(X) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros((0, self.param_dim)), np.zeros(0)
        rows = self.searcher.search_rows(X, accept=self._accept)
        pt, ent, par, dist, ok = with_boundary(self, X, *rows)
        best = best_per_group(pt, (~ok, dist), len(X))  # every point has a row
        found = ok[best]
        return np.where(found, ent[best], -1).astype(np.int64), par[best], np.where(found, dist[best], np.inf)

    # ------------------------------------------------------------------
    # the stages: attach (cad.attach), place and project (cad.place)
    # ------------------------------------------------------------------
    def attach(
        self,
        facet_points: npt.ArrayLike,
        nodes: npt.ArrayLike | None = None,
        *,
        faces: npt.ArrayLike | None = None,
        seeds: npt.ArrayLike | None = None,
        comm: Any = None,
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
        return _attach.attach(self, facet_points, nodes, faces, seeds, comm)

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
        self._hints = MeshHints.from_facets(facet_nodes, faces, params, self.param_dim)

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
        return _place.place(self, records, straight)

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
        return _place.project(self, records, points)

    # ------------------------------------------------------------------
    # normals
    # ------------------------------------------------------------------
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
        g = Groups(ent)
        if d == 1:
            for e, sl in g:  # loop over entities
                sel = g.order[sl]
                c = self.entities[e]
                _, T = evaluate_params(c, normalize_params(c, P[sel]), 1)
                t = T[:, 0] / np.maximum(np.linalg.norm(T[:, 0], axis=1, keepdims=True), 1e-300)
                out[sel] = np.stack([t[:, 1], -t[:, 0], np.zeros(len(sel))], axis=1)
            return (out * sign[:, None]).reshape(nf, nfv, 3)
        centre = np.repeat(params[:, :, :d].mean(axis=1), nfv, axis=0)
        for e, sl in g:  # loop over entities
            sel = g.order[sl]
            s = self.entities[e]
            if hasattr(s, "normals"):
                out[sel] = s.normals(P[sel])
                continue
            n = unit_normals(self.entities, ent[sel], P[sel])
            bad = np.linalg.norm(n, axis=1) == 0
            if bad.any():
                nudge = P[sel][bad] + NORMAL_NUDGE * (centre[sel][bad] - P[sel][bad])
                n[bad] = unit_normals(self.entities, ent[sel][bad], nudge)
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
        if self._curve_edges is None:  # curves of a model not made by from_model: unknown
            return sign
        pos = np.full(len(self.model.edges), -1, dtype=np.int64)
        pos[self._curve_edges] = np.arange(len(self._curve_edges))
        for f in self.model.faces:
            up = np.sign(np.cross(f.surface.X, f.surface.Y)[2]) * (-1.0 if f.reversed else 1.0)
            for lp in f.loops:
                e = pos[lp.uses]
                sign[e[e >= 0]] = lp.use_senses[e >= 0] * (up if up != 0 else 1.0)
        return sign
