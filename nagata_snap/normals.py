"""Vertex normals of a polyhedral boundary, with sharp creases kept sharp.

Each boundary facet corner (facet, local vertex) gets one unit normal.  Corners
of the same vertex share that normal when they are joined across smooth
ridges; a crease (dihedral angle above a threshold, or a change of facet tag)
separates them, so a vertex on a crease has one normal per smooth side
(Nagata 2005, sec. 2.1.2, "multiple normals").

Estimated normals use Max's (1999) weighting, which Neto (2010, seed 000,
sec. 4.1.3, eq. 22) found best overall ("MWSELR")::

    n ~ sum_i n_i sin(alpha_i) / (|e_i| |e_i+1|)

over the facets ``i`` of the sector around the vertex, ``alpha_i`` the facet
angle at the vertex between its edges ``e_i, e_i+1``.  In 2D the analogue is
``n ~ sum_i n_i / |e_i|`` (edge-length reciprocals), which, like MWSELR on a
sphere, is exact for vertices on a circle: a chord of length
``|e| = 2 R sin(beta)`` has its normal at angle ``beta`` from the vertex
normal, so weights ``1/|e|`` cancel the tangential parts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

__all__ = ["NormalsError", "NonManifoldError", "CornerNormals", "corner_normals", "corner_weights"]


class NormalsError(ValueError):
    """Normals that are zero, NaN, or opposite where they must agree."""


class NonManifoldError(ValueError):
    """A boundary ridge (2D vertex, 3D edge) shared by other than two boundary facets."""


@dataclass
class CornerNormals:
    """Normals per facet corner and the ridge structure they were built on.

    Attributes:
        normals: ``(F, nfv, 3)`` unit normal of each corner.
        sector: ``(F, nfv)`` int label of the smooth sector of each corner;
            corners with equal labels share a normal.
        vertex: ``(F, nfv)`` index of each corner's vertex into the unique vertices.
        ridge_facets: ``(R, 2)`` the two facets of each ridge (3D: edge, 2D: vertex).
        ridge_vertices: ``(R, nfv - 1)`` vertex indices of each ridge.
        crease: ``(R,)`` bool, True where the ridge separates sectors.
    """

    normals: np.ndarray
    sector: np.ndarray
    vertex: np.ndarray
    ridge_facets: np.ndarray
    ridge_vertices: np.ndarray
    crease: np.ndarray


def corner_weights(x: np.ndarray) -> np.ndarray:
    """Weights of each facet corner in the vertex-normal average.

    Args:
        x: ``(F, nfv, 3)`` facet vertex coordinates.

    Returns:
        ``(F, nfv)``: 3D ``sin(alpha)/(|e1||e2|) = |e1 x e2| / (|e1|^2 |e2|^2)``
        (MWSELR); 2D ``1/|e|``.
    """
    nfv = x.shape[1]
    if nfv == 2:
        w = 1.0 / np.linalg.norm(x[:, 1] - x[:, 0], axis=1)
        return np.stack([w, w], axis=1)
    w = np.empty(x.shape[:2])
    for i in range(3):  # three corners, vectorised over facets
        e1 = x[:, (i + 1) % 3] - x[:, i]
        e2 = x[:, (i + 2) % 3] - x[:, i]
        w[:, i] = np.linalg.norm(np.cross(e1, e2), axis=1) / (
            np.einsum("ij,ij->i", e1, e1) * np.einsum("ij,ij->i", e2, e2)
        )
    return w


def _ridges(vid: np.ndarray, x: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ridges (2D: vertices, 3D: edges) of a facet set, each with its two facets.

    ``x (F, nfv, 3)``, if given, only serves to name the first bad ridge's
    coordinates in the :class:`NonManifoldError` message.

    Returns ``(ridge_vertices (R, nfv-1), ridge_facets (R, 2), ridge_local (R, 2, nfv-1))``
    where ``ridge_local[r, s, :]`` are the local positions of the ridge's
    vertices in facet ``ridge_facets[r, s]``.
    """
    F, nfv = vid.shape
    if nfv == 2:
        local = np.array([[0], [1]])
    else:
        local = np.array([[0, 1], [1, 2], [0, 2]])
    nr = local.shape[0]
    keys = vid[:, local]  # (F, nr, nfv-1)
    order = np.argsort(keys, axis=2)
    keys = np.take_along_axis(keys, order, axis=2).reshape(F * nr, nfv - 1)
    loc = np.take_along_axis(np.broadcast_to(local, (F, nr, nfv - 1)), order, axis=2)
    loc = loc.reshape(F * nr, nfv - 1)
    fac = np.repeat(np.arange(F), nr)
    uniq, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    bad = np.flatnonzero(counts != 2)
    if len(bad):
        where = f"vertex ids {uniq[bad[0]].tolist()}"
        if x is not None:
            slot = np.flatnonzero(inv == bad[0])[0]  # first facet corner(s) of that ridge
            where = f"{np.round(x[fac[slot], loc[slot]], 6).tolist()}"
        raise NonManifoldError(
            f"{len(bad)} boundary {'vertices' if nfv == 2 else 'edges'} are shared by "
            f"{sorted(set(counts[bad].tolist()))} boundary facets instead of 2 "
            f"(non-manifold boundary, e.g. cells touching only at "
            f"{'a vertex' if nfv == 2 else 'an edge'}, or an open surface); first at {where}"
        )
    srt = np.argsort(inv, kind="stable")
    fac2 = fac[srt].reshape(-1, 2)
    loc2 = loc[srt].reshape(-1, 2, nfv - 1)
    return uniq, fac2, loc2


def corner_normals(
    vid: np.ndarray,
    x: np.ndarray,
    facet_normal: np.ndarray,
    tag: np.ndarray,
    crease_angle: float = 60.0,
    split_tags: bool = True,
) -> CornerNormals:
    """Estimate one normal per smooth side at every boundary vertex.

    Args:
        vid: ``(F, nfv)`` vertex index of each facet corner (shared vertices equal).
        x: ``(F, nfv, 3)`` corner coordinates.
        facet_normal: ``(F, 3)`` unit outward facet normals.
        tag: ``(F,)`` facet tags.
        crease_angle: dihedral angle in degrees above which a ridge is a crease.
        split_tags: treat ridges between facets of different tags as creases.

    Returns:
        :class:`CornerNormals`.
    """
    F, nfv = vid.shape
    rv, rf, rl = _ridges(vid, x)
    cosang = np.einsum("ij,ij->i", facet_normal[rf[:, 0]], facet_normal[rf[:, 1]])
    crease = cosang < np.cos(np.radians(crease_angle))
    if split_tags:
        crease |= tag[rf[:, 0]] != tag[rf[:, 1]]
    smooth = np.flatnonzero(~crease)
    # join the corners of each ridge vertex across smooth ridges
    a = (rf[smooth, 0, None] * nfv + rl[smooth, 0, :]).ravel()
    b = (rf[smooth, 1, None] * nfv + rl[smooth, 1, :]).ravel()
    graph = scipy.sparse.coo_matrix((np.ones(len(a)), (a, b)), shape=(F * nfv, F * nfv))
    _, label = scipy.sparse.csgraph.connected_components(graph, directed=False)
    w = corner_weights(x).ravel()
    contrib = w[:, None] * np.repeat(facet_normal, nfv, axis=0)
    sums = np.zeros((label.max() + 1, 3))
    np.add.at(sums, label, contrib)
    norm = np.linalg.norm(sums, axis=1)
    if np.any(~(norm > 1e-300)):
        raise NormalsError(
            f"{np.count_nonzero(~(norm > 1e-300))} boundary vertices have a zero or NaN "
            "estimated normal (facets around them cancel out or are degenerate)"
        )
    n = (sums / norm[:, None])[label].reshape(F, nfv, 3)
    return CornerNormals(n, label.reshape(F, nfv), vid, rf, rv, crease)
