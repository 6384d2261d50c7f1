"""What the snapper asks of a geometry, and what a geometry reports back.

Two geometries implement it: :class:`~nagata_snap.nagata.geometry.NagataGeometry`
(patches rebuilt from the coarse boundary) and
:class:`~nagata_snap.cad.geometry.CadGeometry` (faces, edges and corners of a
CAD model).  :meth:`place` of either returns a :class:`PlaceReport`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["PlaceReport"]


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
        """One line ``name value, ...`` of every field (for ``--report`` output)."""
        return ", ".join(f"{f.name} {getattr(self, f.name)}" for f in dataclasses.fields(self))
