"""The refinement hook: ``dolfinx.mesh.refine`` followed by boundary snapping.

:class:`Snapper` replaces ``dolfinx.mesh.refine`` in an adaptive loop::

    geometry = NagataGeometry(mesh, facet_tags, tags=[CYLINDER])
    snapper = Snapper(mesh, facet_tags, geometry)
    for level in range(5):
        ...solve, estimate, mark...
        mesh, facet_tags, parent_cell, parent_facet, report = snapper.refine(mesh, edges)

Each call refines the mesh it returned last (or the coarse mesh), places the
new vertices of the snapped facets on the geometry from their lineage records
(no search), smooths the interior in a band around them, checks (and if
needed repairs) inverted or degenerate cells, and transfers the facet tags.  The
mesh passed in is never modified; a failure raises before anything is returned.
The snapper keeps the last refinement's parent-cell map (in the refined
mesh's final cell order), so :meth:`Snapper.transfer` carries a solution from
the mesh given to ``refine`` to the one it returned without a point search.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import dolfinx.fem
import dolfinx.mesh
import numpy as np
import numpy.typing as npt
from mpi4py import MPI

from nagata_snap.curved import CurvedInfo, curved_mesh
from nagata_snap.geometry import PlaceReport, SnapGeometry
from nagata_snap.mesh import bisect
from nagata_snap.mesh.boundary import (
    BoundaryFacets,
    boundary_facets,
    cell_facets_of,
    check_snap_input,
    facets_of_cells,
    tag_values,
    update_nodes,
)
from nagata_snap.mesh.lineage import LineageError, child_facets, child_interior_facets
from nagata_snap.mesh.parallel import collective, collective_place, split_facets
from nagata_snap.mesh.records import Records, refine_records
from nagata_snap.smoothing.kernels import warm_up
from nagata_snap.smoothing.quality import QualityReport, degenerate_cells
from nagata_snap.smoothing.repair import InvertedCellsError, RepairResult, repair
from nagata_snap.smoothing.slide import SlidingBoundary
from nagata_snap.transfer import TransferInfo, transfer

__all__ = ["Snapper", "Refined", "SnapReport", "InvertedCellsError", "LineageError", "MOVED_RTOL"]

#: A snapped vertex counts as moved (``SnapReport.boundary_vertices_moved``) if
#: its move exceeds this fraction of the model size (the coarse mesh's
#: bounding-box diagonal): the tolerance to which serial and MPI runs agree.
MOVED_RTOL = 1e-12


@dataclass
class SnapReport:
    """What one :meth:`Snapper.refine` call did (numbers are global over processes).

    Attributes:
        level: refinement level reached (1 after the first call).
        num_cells, num_vertices: size of the refined mesh.
        boundary_vertices_moved: snapped vertices that moved off their straight position
            by more than :data:`MOVED_RTOL` of the model size (a vertex the geometry
            puts where it already was, up to round-off, is not counted: its
            round-off depends on the order of the facets, i.e. on the partition).
        max_displacement: largest snapping move (length unit).
        inverted_before_smoothing: cells inverted or degenerate with the boundary
            snapped and the interior not yet smoothed.
        inverted_after_smoothing: always 0 in a returned report.
        repair_stage: ``'smooth'``, ``'untangle'``, ``'slide'`` or ``'partial'``
            (see :mod:`nagata_snap.smoothing.repair`).
        partially_moved, max_shortfall: vertices left short of the geometry and
            the largest remaining distance (length unit); printed by ``str``.
        slid_vertices: boundary vertices that slid along the geometry to make
            room (still on it; their records follow them).
        times: seconds per stage (``refine``, ``lineage``, ``place``, ``smooth+check``,
            ``tags``: the facet tags of the refined mesh, i.e. its facet entities
            and the MeshTags, which a loop without snapping pays in
            ``transfer_meshtag`` too).
        geometry: the geometry's placement report (CAD: residuals, Newton histogram).
        quality: :class:`~nagata_snap.smoothing.quality.QualityReport` (None if switched off).
        smoothing_attempts: one dict per smoothing / repair attempt: ``stage``,
            ``layers``, ``cells`` and ``nodes`` it worked on, ``seconds``,
            ``n_bad`` (bad cells left), see :class:`~nagata_snap.smoothing.repair.RepairResult`.
    """

    level: int
    num_cells: int
    num_vertices: int
    boundary_vertices_moved: int
    max_displacement: float
    inverted_before_smoothing: int
    inverted_after_smoothing: int
    repair_stage: str
    partially_moved: int
    max_shortfall: float
    times: dict[str, float] = field(default_factory=dict)
    geometry: PlaceReport = field(default_factory=PlaceReport)
    quality: QualityReport | None = None
    smoothing_attempts: list[dict] = field(default_factory=list)
    slid_vertices: int = 0

    def shortfall_note(self) -> str:
        """``"N vertices left short of the geometry (max shortfall D)"``, or ``""`` if none."""
        if not self.partially_moved:
            return ""
        return (f"{self.partially_moved} vertices left short of the geometry (max shortfall "
                f"{self.max_shortfall:.3e})")

    def __str__(self) -> str:
        t = ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in self.times.items())
        part = f"; {self.shortfall_note()}" if self.partially_moved else ""
        slid = f", {self.slid_vertices} slid on the geometry" if self.slid_vertices else ""
        return (
            f"level {self.level}: {self.num_cells} cells, {self.num_vertices} vertices, "
            f"{self.boundary_vertices_moved} boundary vertices moved (max {self.max_displacement:.3e}), "
            f"inverted cells {self.inverted_before_smoothing} before smoothing, "
            f"{self.inverted_after_smoothing} after ({self.repair_stage}{slid}){part}; {t}"
        )


class Refined(NamedTuple):
    """Result of :meth:`Snapper.refine`."""

    mesh: dolfinx.mesh.Mesh
    facet_tags: dolfinx.mesh.MeshTags
    parent_cell: npt.NDArray[np.int32]
    parent_facet: npt.NDArray[np.int8]
    report: SnapReport


@dataclass(frozen=True)
class _Level:
    """One level of the hierarchy: its mesh, boundary facets, tags and records."""

    mesh: dolfinx.mesh.Mesh
    boundary: BoundaryFacets
    tag: np.ndarray  # (nf,) facet tag values (-1 untagged)
    snapped: np.ndarray  # (nf,) bool
    records: Records  # records of the snapped facets, in order
    interior_cells: np.ndarray  # (ni,) tagged facets that are not exterior (interfaces),
    interior_local: np.ndarray  # (ni,)  as owned cell / local facet pairs (once per side)
    interior_tag: np.ndarray  # (ni,) their tags


class _LastRefine(NamedTuple):
    parent: dolfinx.mesh.Mesh  # the mesh given to refine
    parent_cells: np.ndarray  # (owned cells of child,) its cell of each child, final order
    child: dolfinx.mesh.Mesh  # the mesh refine returned


class Snapper:
    """Refine-and-snap hook for adaptive loops.

    Args:
        mesh: the coarse mesh the geometry describes.
        facet_tags: its facet tags (transferred to every refined level).
        geometry: a :class:`~nagata_snap.geometry.SnapGeometry`:
            :class:`~nagata_snap.nagata.geometry.NagataGeometry` or
            :class:`~nagata_snap.cad.CadGeometry`.
        tags: facet tag values to snap; default ``geometry.tags``, or all tags
            if that is None.
        smoothing: interior smoothing after the boundary moved: ``'elastic'``
            (default: a few Jacobi averaging sweeps over a band of cells, and the
            stiffened linear-elastic extension, PETSc CG + Jacobi, only near the
            cells they leave bad or poor; ``smoothing_options={"first_sweeps": 0}``
            solves it over the whole band), ``'laplace'`` (Jacobi averaging
            sweeps to convergence) or ``'none'``.
        repair: on inverted or degenerate cells, untangle the neighbourhood of
            the bad cells (interior nodes), then let nearby snapped boundary
            vertices slide on the geometry, then, as the last resort, move the
            offending boundary vertices only part of the way (reported).  With
            ``False`` any bad cell raises.
        min_fraction: smallest acceptable fraction of a vertex's move (0..1);
            if repair needs less, :class:`InvertedCellsError` is raised.
        min_quality: mean-ratio floor (0..1) below which a changed cell counts
            as degenerate (cells already poor before snapping only if they lose
            half their quality).
        smoothing_options: options of :func:`nagata_snap.smoothing.smooth.smooth`
            (``layers``, ``exponent``, ``solver``, ...).
        quality_report: build a :class:`~nagata_snap.smoothing.quality.QualityReport`
            each level: ``True`` / ``"changed"`` (default): angles and ratios
            of the cells that snapping and smoothing changed (O(band) work);
            ``"all"``: of every cell (O(mesh) work);
            ``False``: none.
        verbose: print the per-level report on rank 0.
    """

    def __init__(
        self,
        mesh: dolfinx.mesh.Mesh,
        facet_tags: dolfinx.mesh.MeshTags,
        geometry: SnapGeometry,
        tags: Sequence[int] | None = None,
        *,
        smoothing: str = "elastic",
        repair: bool = True,
        min_fraction: float = 0.0,
        min_quality: float = 0.01,
        smoothing_options: dict | None = None,
        quality_report: bool | str = True,
        verbose: bool = False,
    ):
        _check_options(smoothing, min_fraction, min_quality, quality_report)
        self.tags = check_snap_input(mesh, facet_tags, geometry.tags if tags is None else tags)
        _check_cells(mesh)
        self.geometry = geometry
        self.smoothing = smoothing
        self.repair = bool(repair)
        self.min_fraction = float(min_fraction)
        self.min_quality = float(min_quality)
        self.smoothing_options = dict(smoothing_options or {})
        self.quality_report = quality_report
        self.verbose = verbose
        self.comm = mesh.comm
        warm_up()  # the guard's compiled kernels, loaded once per process, not in a level
        self._level = self._coarse_level(mesh, facet_tags)
        self.model_size = _model_size(mesh)
        self._last: _LastRefine | None = None
        self.level = 0
        #: the stage :meth:`refine` is in (a key of ``report.times``, or ``"report"``), None
        #: between calls; for progress output from another thread (the CLI's heartbeat)
        self.stage: str | None = None

    def _coarse_level(self, mesh: dolfinx.mesh.Mesh, facet_tags: dolfinx.mesh.MeshTags) -> _Level:
        """The coarse mesh's boundary facets, their tags and records, and its tagged interfaces."""
        bf = boundary_facets(mesh)
        tag = tag_values(facet_tags, bf.facet_indices(mesh))
        snapped = np.isin(tag, self.tags)
        # tagged facets that are not on the exterior boundary (interfaces): kept through refine
        fmap = mesh.topology.index_map(mesh.topology.dim - 1)
        ext = np.zeros(fmap.size_local + fmap.num_ghosts, dtype=bool)
        ext[bf.facet_indices(mesh)] = True
        ext[dolfinx.mesh.exterior_facet_indices(mesh.topology)] = True
        inner = ~ext[facet_tags.indices]
        int_cells, int_local, which = cell_facets_of(mesh, np.asarray(facet_tags.indices[inner], dtype=np.int32))
        interior_tag = np.asarray(facet_tags.values[inner], dtype=np.int64)[which]
        x = mesh.geometry.x
        gids = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)
        nodes = bf.nodes[snapped]
        # CAD: facet edges on CAD edges are found over all processes (collective)
        records = collective(self.comm, lambda: self.geometry.attach(x[nodes], nodes=gids[nodes],
                                                                     comm=self.comm))
        return _Level(mesh, bf, tag, snapped, records, int_cells, int_local, interior_tag)

    @property
    def mesh(self) -> dolfinx.mesh.Mesh:
        """The mesh of the current level (the one :meth:`refine` expects)."""
        return self._level.mesh

    def curved_mesh(self, degree: int = 2, **kwargs) -> tuple[dolfinx.mesh.Mesh, CurvedInfo]:
        """Degree-``degree`` version of the current level's mesh, boundary nodes on the geometry.

        The result shares the straight mesh's topology, so its facet tags and
        ``parent_cell`` maps apply unchanged; keep refining the straight mesh.
        See :func:`nagata_snap.curved.curved_mesh` (``kwargs``: ``variant``,
        ``min_ratio``, ``max_bisections``).

        Args:
            degree: degree of the coordinate element, 2 (default), 3 or 4.

        Returns:
            ``(mesh, info)``.
        """
        lv = self._level
        return curved_mesh(lv.mesh, lv.boundary, lv.snapped, lv.records, self.geometry,
                           degree=degree, **kwargs)

    def refine(
        self, mesh: dolfinx.mesh.Mesh, edges: npt.ArrayLike | None = None
    ) -> Refined:
        """Refine ``mesh`` (all cells, or the given edges) and snap its new boundary vertices.

        The stages, each a method: :meth:`_bisect` (``dolfinx.mesh.refine``, its ties
        among equally long edges broken by position, so that the cells are the same on
        any number of processes: :mod:`nagata_snap.mesh.bisect`),
        :meth:`_lineage` (child facets and their records), :meth:`_place`
        (new boundary vertices onto the geometry), :meth:`_guard` (smoothing,
        check and repair of the cells), :meth:`_facet_tags` and
        :meth:`_report`; ``report.times`` holds the seconds of each.

        Args:
            mesh: the mesh returned by the previous call (or the coarse mesh).
            edges: local indices of edges to bisect, as for ``dolfinx.mesh.refine``;
                ``None`` refines uniformly.

        Returns:
            :class:`Refined` ``(mesh, facet_tags, parent_cell, parent_facet, report)``;
            ``parent_cell``/``parent_facet`` are exactly what ``dolfinx.mesh.refine``
            returned, so ``dolfinx.mesh.transfer_meshtag`` and interpolation
            between levels keep working.

        Raises:
            LineageError: ``mesh`` is not the mesh this snapper returned last.
            InvertedCellsError: no valid mesh within ``min_fraction`` (nothing is returned).
            CadError: CAD projection failed for some vertices (nothing is returned).
        """
        prev = self._level
        if mesh is not prev.mesh:
            raise LineageError(
                "Snapper.refine expects the mesh it returned last (or the coarse mesh it was "
                "built on); got a different mesh object"
            )
        times: dict[str, float] = {}
        with self._timed(times, "refine"):
            mesh1, parent_cell, parent_facet = self._bisect(mesh, edges)
        with self._timed(times, "lineage"):
            level, parent_cells = self._lineage(prev, mesh1, parent_cell)
        with self._timed(times, "place"):
            x_ref, moved, records, placed = self._place(level)
        level = dataclasses.replace(level, records=records)
        with self._timed(times, "smooth+check"):
            res, records = self._guard(level, x_ref, moved)
        level = dataclasses.replace(level, records=records)
        with self._timed(times, "tags"):
            ft1 = self._facet_tags(level)
        with self._in_stage("report"):  # (not in times: the report holds them)
            report = self._report(level, x_ref, moved, res, placed, times)
        self._level = level
        self._last = _LastRefine(mesh, parent_cells, mesh1)
        self.level += 1
        if self.verbose and self.comm.rank == 0:
            print(report, flush=True)
        return Refined(mesh1, ft1, parent_cell, parent_facet, report)

    @contextlib.contextmanager
    def _in_stage(self, stage: str) -> Iterator[None]:
        """Run the ``with`` block as :attr:`stage` ``stage`` (None again after it)."""
        self.stage = stage
        try:
            yield
        finally:
            self.stage = None

    @contextlib.contextmanager
    def _timed(self, times: dict[str, float], stage: str) -> Iterator[None]:
        """:meth:`_in_stage` ``stage``, its seconds recorded as ``times[stage]``."""
        t0 = time.perf_counter()
        with self._in_stage(stage):
            yield
        times[stage] = time.perf_counter() - t0

    @staticmethod
    def _bisect(mesh: dolfinx.mesh.Mesh, edges: npt.ArrayLike | None
                ) -> tuple[dolfinx.mesh.Mesh, npt.NDArray[np.int32], npt.NDArray[np.int8]]:
        """``dolfinx.mesh.refine`` of ``mesh`` (marked ``edges`` checked first), with parent maps,
        its ties among longest edges broken by position (:func:`nagata_snap.mesh.bisect.refine`)."""
        mesh.topology.create_entities(1)
        marked = None if edges is None else _check_edges(mesh, edges)
        return bisect.refine(mesh, marked)

    def _lineage(self, prev: _Level, mesh1: dolfinx.mesh.Mesh, parent_cell: npt.NDArray[np.int32]
                 ) -> tuple[_Level, np.ndarray]:
        """The refined level: child facets of ``prev``'s facets, their tags and (refined) records,
        and the parent cell of every owned cell of ``mesh1``, in its final order."""
        def lineage():  # no MPI inside: a LineageError on one process is raised on all
            ch = child_facets(prev.mesh, prev.boundary, mesh1, parent_cell)
            return ch, child_interior_facets(prev.mesh, prev.interior_cells, prev.interior_local,
                                             mesh1, ch.parent_cells)

        ch, (c_int, l_int, i_int) = collective(self.comm, lineage)
        snapped = prev.snapped[ch.parent]
        row = np.cumsum(prev.snapped) - 1  # boundary facet -> row of prev.records
        sel = np.flatnonzero(snapped)
        records = refine_records(prev.records, row[ch.parent[sel]], ch.weights[sel])
        level = _Level(mesh1, ch.boundary, prev.tag[ch.parent], snapped, records, c_int, l_int,
                       prev.interior_tag[i_int])
        return level, ch.parent_cells

    def _place(self, level: _Level) -> tuple[np.ndarray, np.ndarray, Records, PlaceReport]:
        """Move the vertices of the snapped facets of ``level.mesh`` onto the geometry (in place).

        Returns:
            ``(x_ref (n, 3), moved (n,), records, report)``: the straight
            coordinates of all local nodes, the nodes that received a
            position, the snapped facets' records as the geometry returned
            them, the geometry's report.
        """
        x = level.mesh.geometry.x
        x_ref = x.copy()
        nodes = level.boundary.nodes[level.snapped]
        pts, records, placed = collective_place(
            self.comm, self.geometry, level.records, x[nodes],
            f"new boundary vertices at level {self.level + 1}",
            split=split_facets(level.mesh.geometry.index_map(), nodes))
        moved = update_nodes(level.mesh, x, nodes.ravel(), pts.reshape(-1, 3))
        return x_ref, moved, records, placed

    def _guard(self, level: _Level, x_ref: np.ndarray, moved: np.ndarray) -> tuple[RepairResult, Records]:
        """Smooth the interior, check the cells and repair bad ones (:func:`~nagata_snap.smoothing.repair.repair`).

        Writes the result into ``level.mesh``; returns it and the snapped
        facets' records (changed where vertices slid on the geometry).
        """
        x = level.mesh.geometry.x
        # boundary nodes that do not move are held; listing them (from the
        # lineage) spares smoothing the O(mesh) search for exterior facets
        opts = dict(self.smoothing_options)
        hold = level.boundary.nodes.ravel() if opts.pop("fix_boundary", True) else np.zeros(0, np.int32)
        # snapped vertices may slide on the geometry (not those of unsnapped facets)
        slide = SlidingBoundary(level.boundary.nodes[level.snapped], level.records, self.geometry,
                                level.boundary.nodes[~level.snapped]) if self.repair else None
        res = repair(
            level.mesh,
            x_ref,
            x,
            np.flatnonzero(moved).astype(np.int32),
            hold,
            method=self.smoothing,
            min_quality=self.min_quality,
            untangle=self.repair,
            slide=slide,
            allow_partial=self.repair,
            min_fraction=self.min_fraction,
            report=self.quality_report,
            fix_boundary=False,
            **opts,
        )
        x[:] = res.x
        return res, (slide.records if slide is not None else level.records)

    def _report(self, level: _Level, x_ref: np.ndarray, moved: np.ndarray, res: RepairResult,
                placed: PlaceReport, times: dict[str, float]) -> SnapReport:
        """The :class:`SnapReport` of the level just built (global numbers, collective)."""
        mesh1 = level.mesh
        x = mesh1.geometry.x
        imap = mesh1.geometry.index_map()
        n_own = imap.size_local
        disp = np.linalg.norm(x[:n_own] - x_ref[:n_own], axis=1)
        moved_owned = moved[:n_own] & (disp > MOVED_RTOL * self.model_size)
        short = np.zeros(len(x))
        short[np.flatnonzero(moved)] = res.shortfall
        short = short[:n_own]
        return SnapReport(
            level=self.level + 1,
            num_cells=mesh1.topology.index_map(mesh1.topology.dim).size_global,
            num_vertices=imap.size_global,
            boundary_vertices_moved=self.comm.allreduce(int(moved_owned.sum())),
            max_displacement=self.comm.allreduce(float(disp.max(initial=0.0)), op=MPI.MAX),
            inverted_before_smoothing=res.n_inverted_unsmoothed,
            inverted_after_smoothing=0,
            repair_stage=res.stage,
            partially_moved=self.comm.allreduce(int(np.count_nonzero(short > 0))),
            max_shortfall=self.comm.allreduce(float(short.max(initial=0.0)), op=MPI.MAX),
            times=times,
            geometry=placed,
            quality=res.report,
            smoothing_attempts=list(res.attempts),
            slid_vertices=res.slid,
        )

    @property
    def parent_cells(self) -> npt.NDArray[np.int32]:
        """Parent cell (local, in the mesh given to the last :meth:`refine`) of every owned
        cell of the mesh it returned, in that mesh's final cell order.

        Unlike DOLFINx 0.11's ``parent_cell``, it is indexed by the refined
        mesh's cells as numbered (see :func:`nagata_snap.mesh.lineage.parent_cells`).
        Maps of successive levels compose (``P1[P2]`` maps level-2 cells to
        level 0), for :func:`nagata_snap.transfer.transfer` across levels.
        """
        if self._last is None:
            raise ValueError("no refinement yet: call Snapper.refine first")
        return self._last.parent_cells

    def transfer(self, u: dolfinx.fem.Function, V: dolfinx.fem.FunctionSpace, **kwargs
                 ) -> dolfinx.fem.Function | tuple[dolfinx.fem.Function, TransferInfo]:
        """Carry ``u`` from the mesh given to the last :meth:`refine` onto ``V`` on the mesh
        it returned, through the parent cells (no point search, no zero-filled dofs).

        Args:
            u: function on the mesh given to the last ``refine`` call, or on
                a curved mesh of it (:meth:`curved_mesh` before that call).
            V: Lagrange space on the mesh that call returned, or on its curved
                mesh (:meth:`curved_mesh`).
            kwargs: of :func:`nagata_snap.transfer.transfer` (``return_info``).

        For ``u`` from an earlier level, transfer level by level after each
        refine, or compose :attr:`parent_cells` of the levels and call
        :func:`nagata_snap.transfer.transfer` directly.

        Returns:
            The transferred function (see :func:`nagata_snap.transfer.transfer`).
        """
        last = self._last
        if last is None:
            raise ValueError("Snapper.transfer maps the mesh given to the last refine onto the "
                             "mesh it returned: call Snapper.refine first")
        for what, m, want, name in (("u", u.function_space.mesh, last.parent, "given to"),
                                    ("V", V.mesh, last.child, "returned by")):
            if m.topology._cpp_object is not want.topology._cpp_object:
                raise ValueError(
                    f"{what} must live on the mesh {name} the last Snapper.refine call (or on "
                    "its curved_mesh()); for older levels transfer level by level, or compose "
                    "Snapper.parent_cells and call nagata_snap.transfer.transfer"
                )
        return transfer(u, V, last.parent_cells, **kwargs)

    @staticmethod
    def _facet_tags(level: _Level) -> dolfinx.mesh.MeshTags:
        """Facet tags of the refined mesh ``level.mesh``.

        Creates its facets (as ``transfer_meshtag`` needs too) and the
        facet-to-cell connectivity, so the mesh is ready for
        ``locate_dofs_topological`` like a mesh read from gmsh.
        """
        mesh1 = level.mesh
        tdim = mesh1.topology.dim
        facets = np.concatenate([level.boundary.facet_indices(mesh1),
                                 facets_of_cells(mesh1, level.interior_cells, level.interior_local)])
        mesh1.topology.create_connectivity(tdim - 1, tdim)
        tag = np.concatenate([level.tag, level.interior_tag])
        keep = tag >= 0
        f, first = np.unique(facets[keep], return_index=True)
        v = tag[keep][first].astype(np.int32)
        return dolfinx.mesh.meshtags(mesh1, tdim - 1, f.astype(np.int32), v)



def _check_options(smoothing: str, min_fraction: float, min_quality: float,
                   quality_report: bool | str) -> None:
    """``ValueError`` naming the first bad :class:`Snapper` option."""
    if smoothing not in ("elastic", "laplace", "none"):
        raise ValueError(f"smoothing must be 'elastic', 'laplace' or 'none', got {smoothing!r}")
    if not 0.0 <= min_fraction <= 1.0:
        raise ValueError(f"min_fraction must be in [0, 1], got {min_fraction}")
    if not 0.0 <= min_quality <= 1.0:
        raise ValueError(f"min_quality must be in [0, 1], got {min_quality}")
    if quality_report not in (True, False, "changed", "all"):
        raise ValueError(
            f"quality_report must be True, False, 'changed' or 'all', not {quality_report!r}")


def _model_size(mesh: dolfinx.mesh.Mesh) -> float:
    """Bounding-box diagonal of ``mesh``'s nodes over all processes (length unit; collective)."""
    x = mesh.geometry.x
    box = np.r_[-x.min(axis=0, initial=np.inf), x.max(axis=0, initial=-np.inf)]
    mesh.comm.Allreduce(MPI.IN_PLACE, box, op=MPI.MAX)
    return float(np.linalg.norm(box[3:] + box[:3]))


def _check_cells(mesh: dolfinx.mesh.Mesh) -> None:
    """Raise ``ValueError`` (on every process) if the mesh has degenerate cells.

    Bisection keeps refined cells non-degenerate and the guard keeps snapped
    ones valid, so checking the coarse mesh once is enough; a zero-volume
    cell would otherwise reach the smoother as a singular element.
    """
    n = mesh.topology.index_map(mesh.topology.dim).size_local
    cells = mesh.geometry.dofmaps[0][:n]
    bad = degenerate_cells(mesh.geometry.x, cells, mesh.geometry.dim)
    n_bad = mesh.comm.allreduce(int(bad.size))
    if n_bad:
        where = (np.round(mesh.geometry.x[cells[bad[0]]].mean(axis=0), 6).tolist() if bad.size
                 else "another process")
        raise ValueError(
            f"the mesh has {n_bad} degenerate cells (area / volume at most 1e-12 of their "
            f"longest edge to the power {mesh.geometry.dim}); first at {where}. nagata_snap "
            "needs valid simplices: repair or remesh the input"
        )


def _check_edges(mesh: dolfinx.mesh.Mesh, edges: npt.ArrayLike) -> np.ndarray:
    """Validate marked edges before they reach C++ (bad indices corrupt memory there)."""
    e = np.asarray(edges)
    if e.size and not np.issubdtype(e.dtype, np.integer):
        raise TypeError(f"edges must be integer edge indices, got dtype {e.dtype}")
    e = e.astype(np.int32).ravel()
    emap = mesh.topology.index_map(1)
    n = emap.size_local + emap.num_ghosts
    bad = (e < 0) | (e >= n)
    if bad.any():
        raise ValueError(
            f"{int(bad.sum())} marked edge indices are outside 0..{n - 1} (local edges of this "
            f"process), e.g. {e[bad][:3].tolist()}"
        )
    return e
