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
import numpy as np
import numpy.typing as npt

from nagata_snap.errors import LineageError
from nagata_snap.mesh.lineage import match_points, parent_cells, point_weights
from nagata_snap.mesh.parallel import collective

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

    Midpoints as DOLFINx computes them, ``a / 2 + b / 2`` (the rows of
    :func:`~nagata_snap.mesh.lineage.point_weights` applied to the parent's vertices).
    """
    tdim = mesh1.topology.dim
    n0 = mesh0.topology.index_map(tdim).size_local
    P = parent_cells(mesh1, mesh0, parent_cell, np.ones(n0, dtype=bool))
    g1 = mesh1.geometry.dofmaps[0][: len(P)]
    x1, x0 = mesh1.geometry.x, mesh0.geometry.x
    cell_of = np.full(len(x1), -1, dtype=np.int64)  # one owned cell of each node
    cell_of[g1.ravel()] = np.repeat(np.arange(len(g1)), g1.shape[1])
    nodes = np.flatnonzero(cell_of >= 0)
    X = x0[mesh0.geometry.dofmaps[0][P[cell_of[nodes]]]]  # (n, nv, 3) parent vertices
    slack = 2.0 ** (JITTER_BITS + 2) * np.finfo(float).eps * np.max(np.abs(X), axis=(1, 2))
    code = match_points(x1[nodes][:, None, :], X, slack[:, None])[0][:, 0]
    if np.any(code < 0):
        bad = np.flatnonzero(code < 0)
        raise LineageError(
            f"{bad.size} vertices of the refined mesh are neither a vertex nor an edge midpoint of "
            f"their parent cell (first at {x1[nodes[bad[0]]].round(6).tolist()}): "
            "dolfinx.mesh.refine did not return a refinement of the mesh")
    x1[nodes] = np.einsum("nk,nkd->nd", point_weights(X.shape[1])[code], X)
