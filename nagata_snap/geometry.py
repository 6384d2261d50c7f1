"""What the snapper asks of a geometry, and what a geometry reports back.

:class:`SnapGeometry` is the interface :class:`~nagata_snap.snapper.Snapper`,
:func:`~nagata_snap.curved.curved_mesh` and the sliding repair
(:mod:`nagata_snap.smoothing.slide`) use; nothing else of a geometry is
called by them.  Two geometries implement it:
:class:`~nagata_snap.nagata.geometry.NagataGeometry` (patches rebuilt from the
coarse boundary) and :class:`~nagata_snap.cad.geometry.CadGeometry` (faces,
edges and corners of a CAD model).  Their :meth:`~SnapGeometry.place` returns
a :class:`PlaceReport`.

The lineage records (:class:`~nagata_snap.mesh.records.Records`) are opaque
to the snapper: a geometry makes them (``attach``), refinement combines
their parameters barycentrically, and the geometry reads them back
(``place``, ``project``, ``evaluate``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from mpi4py import MPI

    from nagata_snap.mesh.records import Records

__all__ = ["SnapGeometry", "PlaceReport"]


@runtime_checkable
class SnapGeometry(Protocol):
    """A geometry the snapper places boundary vertices on.

    Shapes: ``nf`` facets of ``nfv`` vertices (2 in 2D, 3 in 3D), points in
    3D (``z = 0`` for 2D meshes), lengths in mesh units.  ``attach`` is called
    collectively (every process, its own facets); the others are local.
    ``isinstance(g, SnapGeometry)`` checks that the members exist (mypy
    checks their signatures).
    """

    @property
    def tags(self) -> Sequence[int] | None:
        """Facet tag values snapped by default (None: every tag of the mesh)."""
        ...

    def attach(
        self, points: np.ndarray, /, nodes: np.ndarray | None = None, *, comm: MPI.Comm | None = None
    ) -> Records:
        """Records of the coarse mesh's snapped facets ``points (nf, nfv, 3)``.

        ``nodes (nf, nfv)`` are the vertices' input-global indices, ``comm``
        the mesh's communicator (collective).
        """
        ...

    def place(self, records: Records, straight: np.ndarray, /) -> tuple[np.ndarray, Records, PlaceReport]:
        """Positions ``(nf, nfv, 3)`` of the facet vertices described by ``records`` on the geometry.

        ``straight (nf, nfv, 3)`` are their current (straight) positions; the
        records returned replace the given ones (e.g. converged parameters).
        """
        ...

    def project(self, records: Records, points: np.ndarray, /) -> tuple[np.ndarray, Records]:
        """Closest points ``(nf, nfv, 3)`` of ``points (nf, nfv, 3)`` on each facet's own entity,
        seeded by ``records``, sharp edges and corners kept on their feature; and the new records."""
        ...

    def evaluate(self, root: npt.ArrayLike, params: np.ndarray, /) -> np.ndarray:
        """Points ``(P, k, 3)`` of entities ``root (P,)`` at record parameters ``params (P, k, .)``."""
        ...


@dataclasses.dataclass(frozen=True)
class PlaceReport:
    """Outcome of one ``place(records, straight)`` call, on the calling process.

    Counts are of facet-vertex slots (``n_points``) or of distinct vertices;
    lengths are in mesh units.  A geometry that evaluates its surface exactly
    (Nagata patches) reports only ``n_points``; the projection counts stay 0.
    """

    #: facet-vertex slots placed (``nf * nfv``)
    n_points: int = 0
    #: distinct vertices among them (CAD: projected once each)
    n_vertices: int = 0
    #: largest / mean distance between a vertex's straight and placed position
    max_residual: float = 0.0
    mean_residual: float = 0.0
    #: ``(k,)`` number of points that took ``i`` Newton iterations
    iterations_histogram: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    #: points placed by a fallback seed, not their own record's parameters
    n_fallback: int = 0
    #: points that ended on another face than their record's
    n_off_root: int = 0
    #: points for which no projection converged (left at the straight position)
    n_unresolved: int = 0
    #: points whose projection left their face's trimming loops
    n_left_face: int = 0
    #: vertices placed on a CAD edge, and the largest gap between the faces meeting there
    n_edge_vertices: int = 0
    max_edge_gap: float = 0.0

    def summary(self) -> str:
        """One line ``name value, ...`` of every field (for ``--report`` output): lengths to 4
        digits, the histogram as ``{iterations: points}`` of its nonzero bins.

        >>> print(PlaceReport(6, 3, 0.25, 0.0625, np.array([2, 0, 4]), max_edge_gap=1.23456e-12).summary())
        n_points 6, n_vertices 3, max_residual 0.25, mean_residual 0.0625, iterations_histogram {0: 2, 2: 4},
        n_fallback 0, n_off_root 0, n_unresolved 0, n_left_face 0, n_edge_vertices 0, max_edge_gap 1.235e-12
        """

        def text(v) -> str:
            if isinstance(v, np.ndarray):
                return "{" + ", ".join(f"{i}: {v[i]}" for i in np.flatnonzero(v)) + "}"
            return f"{v:.4g}" if isinstance(v, float) else str(v)

        return ", ".join(f"{f.name} {text(getattr(self, f.name))}" for f in dataclasses.fields(self))
