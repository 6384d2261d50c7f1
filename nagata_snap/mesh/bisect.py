"""``dolfinx.mesh.refine`` whose cells do not depend on the partition.

DOLFINx's Plaza refinement bisects every refined face at its longest edge.
Where two edges of a face are exactly as long (frequent: the two halves of an
edge bisected at the level before, structured parts of a mesher's output), it
takes the edge whose opposite vertex has the larger *global vertex number*, and
those numbers depend on the partition.  The same mesh is then split into other
cells serially and under ``mpiexec -n 2`` (0.65 % of the cells of a corpus
part), and everything that works on cells after it (smoothing, repair) ends
elsewhere.

:func:`refine` breaks the ties by position instead.  Before the refinement the
lowest :data:`JITTER_BITS` bits of each coordinate are flipped by a hash of the
point's other bits (:func:`jitter`, an involution: a second call restores every
coordinate bit for bit).  Equal lengths become unequal, by amounts that depend
on the vertices' positions only, so every process and every partition picks the
same edge; lengths that differed by more than the jitter keep their order.  After
the refinement the coarse coordinates are restored, and every vertex of the
refined mesh is put back exactly where ``dolfinx.mesh.refine`` of the unjittered
mesh puts it: the vertex or the edge midpoint ``(a + b) / 2`` of its parent cell
that it is (:func:`~nagata_snap.mesh.lineage.match_points`).  The result is a
refinement of the mesh as DOLFINx makes it, with ties among longest edges
resolved by a partition-independent rule.

>>> import numpy as np
>>> x = np.array([[0.5, 0.25, 1.5], [1.0, -2.0, 3.0]])
>>> y = x.copy(); jitter(y, 3)
>>> bool(np.any(y != x)), bool(np.all(np.abs(y - x) < 2.0 ** -44 * np.abs(x)))
(True, True)
>>> jitter(y, 3); bool(np.all(y == x))
True
"""

from __future__ import annotations

import dolfinx.mesh
import numba
import numpy as np
import numpy.typing as npt

from nagata_snap.errors import LineageError
from nagata_snap.mesh.lineage import TOL, ULPS, parent_cells
from nagata_snap.mesh.parallel import collective
from nagata_snap.mesh.simplex import local_edges

__all__ = ["JITTER_BITS", "jitter", "refine"]

#: Lowest mantissa bits of each coordinate that :func:`jitter` flips (at most
#: ``2**JITTER_BITS - 1`` units in the last place).
JITTER_BITS = 8

_MIX = (np.uint64(0x9E3779B97F4A7C15), np.uint64(0xC2B2AE3D27D4EB4F), np.uint64(0x165667B19E3779F9))


def jitter(x: np.ndarray, gdim: int) -> None:
    """Flip the low :data:`JITTER_BITS` bits of the first ``gdim`` coordinates of ``x`` in place.

    Each point's bits are a hash of its coordinates without their low bits, so the
    flip is a function of the position alone and a second call undoes the first.

    Args:
        x: ``(n, 3)`` C-contiguous float64 coordinates, changed in place.
        gdim: number of leading columns to change (the others, zeros of a
            planar mesh, stay as they are).
    """
    u = x.view(np.uint64)
    hi = u[:, :gdim] >> np.uint64(JITTER_BITS)
    with np.errstate(over="ignore"):
        h = np.zeros(len(x), dtype=np.uint64)
        for j in range(gdim):
            h ^= hi[:, j] * _MIX[j]
        h ^= h >> np.uint64(29)
        h *= _MIX[0]
        h ^= h >> np.uint64(32)
    mask = np.uint64((1 << JITTER_BITS) - 1)
    for j in range(gdim):
        u[:, j] ^= (h >> np.uint64(8 * j + 3)) & mask


def refine(
    mesh: dolfinx.mesh.Mesh, edges: npt.NDArray[np.int32] | None
) -> tuple[dolfinx.mesh.Mesh, npt.NDArray[np.int32], npt.NDArray[np.int8]]:
    """``dolfinx.mesh.refine(mesh, edges)`` with parent maps, ties among longest edges broken by position.

    Args:
        mesh: a mesh of affine simplices; its coordinates are jittered for the
            refinement and restored bit for bit, whatever happens.
        edges: local indices of the edges to bisect, ``None`` for all.

    Returns:
        ``(refined mesh, parent_cell, parent_facet)`` as ``dolfinx.mesh.refine``
        returns them with ``RefinementOption.parent_cell_and_facet``.

    Raises:
        LineageError: a vertex of the refined mesh is neither a vertex nor an
            edge midpoint of its parent cell (not a refinement).
    """
    x = mesh.geometry.x
    gdim = mesh.geometry.dim
    jitter(x, gdim)
    try:
        mesh1, parent_cell, parent_facet = dolfinx.mesh.refine(
            mesh, edges, option=dolfinx.mesh.RefinementOption.parent_cell_and_facet)
    finally:
        jitter(x, gdim)
    assert parent_cell is not None and parent_facet is not None  # asked for by the option
    collective(mesh.comm, _restore, mesh1, mesh, parent_cell)
    return mesh1, parent_cell, parent_facet


def _restore(mesh1: dolfinx.mesh.Mesh, mesh0: dolfinx.mesh.Mesh, parent_cell: npt.NDArray[np.int32]) -> None:
    """Put every node of ``mesh1`` exactly on the vertex or edge midpoint of its parent cell that it is.

    Midpoints as DOLFINx computes them, ``a / 2 + b / 2``; a node is matched to the
    nearest of its parent's vertices and edge midpoints as in
    :func:`~nagata_snap.mesh.lineage.match_points`, within its tolerance plus the jitter.
    """
    tdim = mesh1.topology.dim
    n0 = mesh0.topology.index_map(tdim).size_local
    P = parent_cells(mesh1, mesh0, parent_cell, np.ones(n0, dtype=bool))
    g1 = mesh1.geometry.dofmaps[0][: len(P)]
    slack = ULPS + 2.0 ** (JITTER_BITS + 2) * np.finfo(float).eps
    bad = _snap_to_parents(g1, P, mesh0.geometry.dofmaps[0], mesh0.geometry.x, mesh1.geometry.x,
                           local_edges(g1.shape[1]), TOL, slack)
    if bad.size:
        raise LineageError(
            f"{bad.size} vertices of the refined mesh are neither a vertex nor an edge midpoint of "
            f"their parent cell (first at {mesh1.geometry.x[bad[0]].round(6).tolist()}): "
            "dolfinx.mesh.refine did not return a refinement of the mesh")


@numba.njit(cache=True, nogil=True)
def _snap_to_parents(g1: np.ndarray, P: np.ndarray, g0: np.ndarray, x0: np.ndarray, x1: np.ndarray,
                     edges: np.ndarray, tol: float, slack: float) -> np.ndarray:
    """Set each node of the cells ``g1`` to the nearest vertex or edge midpoint of its parent
    cell ``P`` (in place in ``x1``), once per node; the nodes farther than ``tol`` x the
    parent's longest edge + ``slack`` x its largest coordinate are returned."""
    nv = g1.shape[1]
    done = np.zeros(x1.shape[0], dtype=np.bool_)
    C = np.empty((nv + edges.shape[0], 3))
    bad = []
    for c in range(g1.shape[0]):
        p = P[c]
        filled = False
        for k in range(nv):
            node = g1[c, k]
            if done[node]:
                continue
            if not filled:  # the parent's vertices, then its edge midpoints as DOLFINx computes them
                big, h2 = 0.0, 0.0
                for q in range(nv):
                    for d in range(3):
                        C[q, d] = x0[g0[p, q], d]
                        big = max(big, abs(C[q, d]))
                for e in range(edges.shape[0]):
                    a, b = edges[e, 0], edges[e, 1]
                    le = 0.0
                    for d in range(3):
                        C[nv + e, d] = (0.0 + C[a, d] * 0.5) + C[b, d] * 0.5  # (signed zeros too)
                        le += (C[a, d] - C[b, d]) ** 2
                    h2 = max(h2, le)
                lim = tol * np.sqrt(h2) + slack * big
                filled = True
            best, q_best = np.inf, 0
            for q in range(C.shape[0]):
                d2 = 0.0
                for d in range(3):
                    d2 += (x1[node, d] - C[q, d]) ** 2
                if d2 < best:
                    best, q_best = d2, q
            done[node] = True
            if np.sqrt(best) > lim:
                bad.append(node)
                continue
            for d in range(3):
                x1[node, d] = C[q_best, d]
    return np.array(bad, dtype=np.int64)
