"""The corner rule of the snapped boundary: which vertices may not move along the geometry.

A boundary vertex is a *corner* if the facets around it lie on ``nfv`` or
more distinct geometric entities (3D: three faces or coarse facets, 2D: two
curves or coarse segments), or on two or more distinct CAD edges.  It is
decided from all facets of the vertex, never from one facet: a facet at a
corner often has only one of its edges on a CAD edge.  The CAD geometry's
placement (:mod:`nagata_snap.cad.place`) keeps corners at their CAD vertex,
and the sliding boundary of the repair (:mod:`nagata_snap.smoothing.slide`)
never slides them.

>>> import numpy as np
>>> vertex = np.array([0, 0, 0, 1, 1, 2])       # vertex of each facet slot
>>> entity = np.array([4, 5, 6, 4, 4, 5])       # the entity of the slot's facet
>>> corner_vertices(vertex, entity, 3, nfv=3)
array([ True, False, False])
"""

from __future__ import annotations

import numpy as np

__all__ = ["corner_vertices"]


def _n_distinct(group: np.ndarray, key: np.ndarray, n: int) -> np.ndarray:
    """``(n,)`` number of distinct ``key (m,)`` values (non-negative ints) in each group ``group (m,)``."""
    if len(group) == 0:
        return np.zeros(n, dtype=np.int64)
    width = int(key.max()) + 1
    pairs = np.unique(group.astype(np.int64) * width + key)
    return np.bincount(pairs // width, minlength=n)


def corner_vertices(
    vertex: np.ndarray, entity: np.ndarray, n_vertices: int, nfv: int, edge: np.ndarray | None = None
) -> np.ndarray:
    """``(n_vertices,)`` bool: the vertices that are corners (see the module docstring).

    Args:
        vertex: ``(m,)`` vertex (``0..n_vertices-1``) of each facet slot.
        entity: ``(m,)`` entity (face, curve or coarse facet; non-negative) of
            the slot's facet.
        n_vertices: number of vertices.
        nfv: vertices per facet: a vertex on ``nfv`` or more entities is a corner.
        edge: optional ``(m,)`` CAD edge (non-negative curve index, ``-1``: none)
            the slot lies on: a vertex on two or more distinct edges is a corner.
    """
    vertex = np.asarray(vertex, dtype=np.int64).reshape(-1)
    corner = _n_distinct(vertex, np.asarray(entity, dtype=np.int64).reshape(-1), n_vertices) >= nfv
    if edge is not None:
        edge = np.asarray(edge, dtype=np.int64).reshape(-1)
        on = edge >= 0
        corner |= _n_distinct(vertex[on], edge[on], n_vertices) >= 2
    return corner
