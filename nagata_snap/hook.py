"""The refinement hook: ``dolfinx.mesh.refine`` followed by boundary snapping.

:class:`Snapper` replaces ``dolfinx.mesh.refine`` in an adaptive loop::

    geometry = NagataGeometry(mesh, facet_tags, tags=[CYLINDER])
    snapper = Snapper(mesh, facet_tags, geometry)
    for level in range(5):
        ...solve, estimate, mark...
        mesh, facet_tags, parent_cell, parent_facet, report = snapper.refine(mesh, edges)

Each call refines the mesh it returned last (or the coarse mesh), places the
new vertices of the snapped facets on the geometry from their lineage records
(no search), checks that no cell inverted, and transfers the facet tags.  The
mesh passed in is never modified; a failure raises before anything is returned.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple, Sequence

import numpy as np
import numpy.typing as npt

import dolfinx.mesh

from .cad import CadError
from .boundary import BoundaryFacets, boundary_facets, check_p1_simplex, tag_values, update_nodes
from .lineage import LineageError, child_facets
from .records import Records, refine_records

__all__ = ["Snapper", "Refined", "SnapReport", "InvertedCellsError", "LineageError"]


class InvertedCellsError(RuntimeError):
    """Snapping would invert or flatten cells; the refined mesh is not returned."""


@dataclass
class SnapReport:
    """What one :meth:`Snapper.refine` call did (numbers are global over processes)."""

    level: int
    num_cells: int
    num_vertices: int
    boundary_vertices_moved: int
    max_displacement: float
    inverted_cells: int
    times: dict[str, float] = field(default_factory=dict)
    geometry: dict = field(default_factory=dict)

    def __str__(self) -> str:
        t = ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in self.times.items())
        return (
            f"level {self.level}: {self.num_cells} cells, {self.num_vertices} vertices, "
            f"{self.boundary_vertices_moved} boundary vertices moved (max {self.max_displacement:.3e}), "
            f"{self.inverted_cells} inverted; {t}"
        )


class Refined(NamedTuple):
    """Result of :meth:`Snapper.refine`."""

    mesh: dolfinx.mesh.Mesh
    facet_tags: dolfinx.mesh.MeshTags
    parent_cell: npt.NDArray[np.int32]
    parent_facet: npt.NDArray[np.int8]
    report: SnapReport


@dataclass
class _Level:
    mesh: dolfinx.mesh.Mesh
    boundary: BoundaryFacets
    tag: np.ndarray  # (nf,) facet tag values (-1 untagged)
    snapped: np.ndarray  # (nf,) bool
    records: Records  # records of the snapped facets, in order


def signed_measure(x: np.ndarray, cells: np.ndarray, tdim: int) -> np.ndarray:
    """Signed area (2D, from x-y) or volume (3D) of simplices ``cells (n, tdim+1)``."""
    p = x[cells]
    e = p[:, 1:, :tdim] - p[:, :1, :tdim]
    return np.linalg.det(e) / (2.0 if tdim == 2 else 6.0)


class Snapper:
    """Refine-and-snap hook for adaptive loops.

    Args:
        mesh: the coarse mesh the geometry describes.
        facet_tags: its facet tags (transferred to every refined level).
        geometry: a :class:`~nagata_snap.geometry.NagataGeometry` or
            :class:`~nagata_snap.cad.CadGeometry`.
        tags: facet tag values to snap; default ``geometry.tags`` (Nagata) or all tags.
        min_quality: a cell counts as inverted when its signed measure after
            snapping is below ``min_quality`` times its measure before snapping.
        verbose: print a one-line report per level on rank 0.
    """

    def __init__(
        self,
        mesh: dolfinx.mesh.Mesh,
        facet_tags: dolfinx.mesh.MeshTags,
        geometry,
        tags: Sequence[int] | None = None,
        *,
        min_quality: float = 1e-3,
        verbose: bool = False,
    ):
        check_p1_simplex(mesh)
        if tags is None:
            tags = getattr(geometry, "tags", None)
        if tags is None:
            tags = np.unique(np.concatenate(mesh.comm.allgather(np.asarray(facet_tags.values))))
        self.tags = [int(t) for t in np.atleast_1d(tags)]
        present = set(np.concatenate(mesh.comm.allgather(np.asarray(facet_tags.values))).tolist())
        missing = sorted(set(self.tags) - present)
        if missing:
            raise ValueError(f"facet tags {missing} do not exist (present: {sorted(present)})")
        self.geometry = geometry
        self.min_quality = float(min_quality)
        self.verbose = verbose
        self.comm = mesh.comm
        bf = boundary_facets(mesh)
        tag = tag_values(facet_tags, bf.facets)
        snapped = np.isin(tag, self.tags)
        x = mesh.geometry.x
        gids = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)
        sel = np.flatnonzero(snapped)
        records = geometry.attach(x[bf.nodes[sel]], nodes=gids[bf.nodes[sel]])
        self._level = _Level(mesh, bf, tag, snapped, records)
        self.level = 0

    @property
    def mesh(self) -> dolfinx.mesh.Mesh:
        """The mesh of the current level (the one :meth:`refine` expects)."""
        return self._level.mesh

    def refine(
        self, mesh: dolfinx.mesh.Mesh, edges: npt.NDArray[np.int32] | None = None
    ) -> Refined:
        """Refine ``mesh`` (all cells, or the given edges) and snap its new boundary vertices.

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
            InvertedCellsError: snapping inverted cells (nothing is returned).
        """
        prev = self._level
        if mesh is not prev.mesh:
            raise LineageError(
                "Snapper.refine expects the mesh it returned last (or the coarse mesh it was "
                "built on); got a different mesh object"
            )
        times: dict[str, float] = {}
        t0 = time.perf_counter()
        tdim = mesh.topology.dim
        mesh.topology.create_entities(1)
        mesh1, parent_cell, parent_facet = dolfinx.mesh.refine(
            mesh, edges, option=dolfinx.mesh.RefinementOption.parent_cell_and_facet
        )
        times["refine"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        ch = child_facets(mesh, prev.boundary, mesh1, parent_cell)
        tag = prev.tag[ch.parent]
        snapped = prev.snapped[ch.parent]
        row = np.cumsum(prev.snapped) - 1  # boundary facet -> row of prev.records
        sel = np.flatnonzero(snapped)
        records = refine_records(prev.records, row[ch.parent[sel]], ch.weights[sel])
        times["lineage"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        x = mesh1.geometry.x
        x_ref = x.copy()
        nodes = ch.boundary.nodes[sel]
        pts, records, geo_report = self.geometry.place(records, x[nodes])
        unresolved = self.comm.allreduce(int(geo_report.get("n_unresolved", 0)))
        if unresolved:
            raise CadError(
                f"{unresolved} new boundary vertices at level {self.level + 1} have no acceptable "
                "projection onto the CAD geometry (Newton and every fallback failed or landed "
                "farther than the local edge length); nothing was returned"
            )
        moved = update_nodes(mesh1, x, nodes.ravel(), pts.reshape(-1, 3))
        times["place"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        bad = self._inverted(mesh1, x_ref, moved)
        times["check"] = time.perf_counter() - t0
        n_bad = self.comm.allreduce(len(bad))
        if n_bad:
            cmap = mesh1.topology.index_map(tdim)
            gl = cmap.local_to_global(bad.astype(np.int32))
            first = sorted(np.concatenate(self.comm.allgather(gl)).tolist())[:10]
            raise InvertedCellsError(
                f"snapping inverts or flattens {n_bad} cells at level {self.level + 1} "
                f"(global cell indices {first}{' ...' if n_bad > 10 else ''}); the coarse mesh is "
                "too coarse near a curved boundary for snapping without interior smoothing"
            )

        ft1 = self._facet_tags(mesh1, ch.boundary.facets, tag)
        imap = mesh1.geometry.index_map()
        disp = np.linalg.norm(x[: imap.size_local] - x_ref[: imap.size_local], axis=1)
        moved_owned = moved[: imap.size_local] & (disp > 0)
        report = SnapReport(
            level=self.level + 1,
            num_cells=mesh1.topology.index_map(tdim).size_global,
            num_vertices=imap.size_global,
            boundary_vertices_moved=self.comm.allreduce(int(moved_owned.sum())),
            max_displacement=self.comm.allreduce(float(disp.max(initial=0.0)), op=_max()),
            inverted_cells=0,
            times=times,
            geometry=geo_report,
        )
        self._level = _Level(mesh1, ch.boundary, tag, snapped, records)
        self.level += 1
        if self.verbose and self.comm.rank == 0:
            print(report, flush=True)
        return Refined(mesh1, ft1, parent_cell, parent_facet, report)

    def _inverted(self, mesh1: dolfinx.mesh.Mesh, x_ref: np.ndarray, moved: np.ndarray) -> np.ndarray:
        tdim = mesh1.topology.dim
        ncell = mesh1.topology.index_map(tdim).size_local
        cells = mesh1.geometry.dofmaps[0][:ncell]
        touch = np.flatnonzero(moved[cells].any(axis=1))
        v0 = signed_measure(x_ref, cells[touch], tdim)
        v1 = signed_measure(mesh1.geometry.x, cells[touch], tdim)
        return touch[v1 / v0 < self.min_quality]

    @staticmethod
    def _facet_tags(mesh1, facets: np.ndarray, tag: np.ndarray) -> dolfinx.mesh.MeshTags:
        keep = tag >= 0
        f, v = facets[keep], tag[keep].astype(np.int32)
        order = np.argsort(f)
        return dolfinx.mesh.meshtags(mesh1, mesh1.topology.dim - 1, f[order], v[order])


def _max():
    from mpi4py import MPI

    return MPI.MAX
