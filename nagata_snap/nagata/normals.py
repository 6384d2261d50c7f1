"""Vertex normals of a polyhedral boundary, with sharp creases kept sharp.

Each boundary facet corner (facet, local vertex) gets one unit normal.  Corners
of the same vertex share that normal when they are joined across smooth
ridges (one *sector*); a crease separates them, so a vertex on a crease has
one normal per smooth side and a corner of three faces has three (Nagata 2005,
sec. 2.1.2, "multiple normals").

Creases (:func:`crease_ridges`).  A ridge (3D edge, 2D vertex) turns by the
angle ``theta`` between its two facets' normals.  It is a crease when

* ``theta >= crease_angle`` (default 60 deg), or
* ``theta >= crease_angle / 3`` and ``theta`` exceeds three times the
  turn the surface makes on either side: the largest turn from the facet
  to the facets around its vertex opposite the ridge (ridges turning by
  ``crease_angle`` or more left out), or
* the two facets carry different tags (``split_tags``).  Such a ridge that
  is smooth by the rules above (a tangent CAD edge) gets the multi-normal
  coefficient, each face is fitted on its own, and the vertices on it keep
  one normal: a planar side's (exact; the blend is tangent to it), else the
  mean of the two sides'.

So a 30-degree ridge between two flat faces is a crease however fine the
mesh (nothing on either side turns), a fillet meeting a plane tangentially is
smooth (the fillet side turns more than the tangent ridge), and a coarse
mesh of a smooth surface, whose neighbouring facets all turn by 40-50
degrees, is not cut into creases (its facets turn alike on both sides).  A
ridge between two curved faces that turns by less than three times their
own facet-to-facet turn (and less than ``crease_angle``) counts as smooth:
lower ``crease_angle`` or use tags (``split_tags``) to keep it sharp.

Normals (``scheme``).  The default ``"jet"`` fits a local surface per sector
(:mod:`nagata_snap.nagata.jets`: fourth order in 3D, exact on spheres and, in 2D,
on circles), starting from Max's (1999) weighting, which Neto (2010, seed 000,
sec. 4.1.3, eq. 22) found best of the facet-normal means ("MWSELR")::

    n ~ sum_i n_i sin(alpha_i) / (|e_i| |e_i+1|)

over the facets ``i`` of the sector, ``alpha_i`` the facet angle at the
vertex between its edges ``e_i, e_i+1``.  The other means of Neto's
comparison (sec. 4.1, eqs. 20-25) are available by name: ``"mwe"``
(equal weights), ``"mwa"`` (angle), ``"mwselr"``, ``"mwaat"`` (area),
``"mwelr"`` (edge-length reciprocals), ``"mwrelr"`` (their square roots).
In 2D the weights are functions of the segment length ``|e|`` (``"mwselr"``
and ``"mwelr"``: ``1/|e|``, exact for vertices on a circle, since a chord
of length ``2 R sin(beta)`` has its normal at angle ``beta`` from the vertex
normal; ``"mwaat"``: ``|e|``; ``"mwrelr"``: ``|e|^-1/2``; ``"mwe"``,
``"mwa"``: 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

from nagata_snap.errors import NonManifoldError, NormalsError
from nagata_snap.nagata.jets import SectorRings, _angle, fit_sector_normals, padded_rows

__all__ = [
    "NormalsError",
    "NonManifoldError",
    "CornerNormals",
    "SCHEMES",
    "corner_normals",
    "corner_weights",
    "crease_ridges",
]

#: Normal estimates by name: the fitted jet (default) and Neto's (2010) weighted means.
SCHEMES = ("jet", "mwe", "mwa", "mwselr", "mwaat", "mwelr", "mwrelr")

#: Ridges turning less than ``CREASE_FLOOR * crease_angle`` are never creases.
CREASE_FLOOR = 1.0 / 3.0

#: A ridge between the floor and ``crease_angle`` is a crease when it turns
#: more than ``CREASE_RATIO`` times the largest turn next to it on either side
#: (2 cuts coarse torus meshes, whose facets turn unevenly with direction).
CREASE_RATIO = 3.0


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
        region: ``(F,)`` int label of each facet's smooth region (facets
            joined across non-crease ridges).
        rings: the sectors' facet rings the jets grew (:class:`~nagata_snap.nagata.jets.SectorRings`,
            kept for fits on the same stencils), or None.
    """

    normals: np.ndarray
    sector: np.ndarray
    vertex: np.ndarray
    ridge_facets: np.ndarray
    ridge_vertices: np.ndarray
    crease: np.ndarray
    region: np.ndarray
    rings: SectorRings | None = None


def corner_weights(x: np.ndarray, scheme: str = "mwselr") -> np.ndarray:
    """Weights of each facet corner in a weighted mean of facet normals.

    Args:
        x: ``(F, nfv, 3)`` facet vertex coordinates.
        scheme: one of Neto's (2010) means (see the module docstring).

    Returns:
        ``(F, nfv)``; 3D ``"mwselr"``: ``sin(alpha)/(|e1||e2|) = |e1 x e2| / (|e1|^2 |e2|^2)``.
    """
    if scheme not in SCHEMES[1:]:
        raise ValueError(f"unknown normal weighting {scheme!r}; choose one of {list(SCHEMES[1:])}")
    nfv = x.shape[1]
    if nfv == 2:
        le = np.linalg.norm(x[:, 1] - x[:, 0], axis=1)
        w = {"mwe": 1.0 + 0 * le, "mwa": 1.0 + 0 * le, "mwselr": 1 / le, "mwaat": le,
             "mwelr": 1 / le, "mwrelr": 1 / np.sqrt(le)}[scheme]
        return np.stack([w, w], axis=1)
    i = np.arange(3)
    e1 = x[:, (i + 1) % 3] - x[:, i]  # (F, 3 corners, 3)
    e2 = x[:, (i + 2) % 3] - x[:, i]
    cross = np.linalg.norm(np.cross(e1, e2), axis=2)
    l1, l2 = np.linalg.norm(e1, axis=2), np.linalg.norm(e2, axis=2)
    if scheme == "mwe":
        return np.ones(x.shape[:2])
    if scheme == "mwa":
        return np.arctan2(cross, np.einsum("fci,fci->fc", e1, e2))
    return {"mwselr": cross / (l1 * l2) ** 2, "mwaat": cross, "mwelr": 1 / (l1 * l2),
            "mwrelr": 1 / np.sqrt(l1 * l2)}[scheme]


def _ridges(vid: np.ndarray, x: np.ndarray | None = None, allow_open: bool = False):
    """Ridges (2D: vertices, 3D: edges) of a facet set, each with its two facets.

    ``x (F, nfv, 3)``, if given, only serves to name the first bad ridge's
    coordinates in the :class:`NonManifoldError` message.  With
    ``allow_open`` ridges of one facet (the boundary of an open surface) are
    accepted and left out of the result.

    Returns ``(ridge_vertices (R, nfv-1), ridge_facets (R, 2), ridge_local (R, 2, nfv-1),
    open_vertices)`` where ``ridge_local[r, s, :]`` are the local positions of
    the ridge's vertices in facet ``ridge_facets[r, s]`` and ``open_vertices``
    the vertex indices on one-facet ridges.
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
    bad = np.flatnonzero((counts != 2) & ~(allow_open & (counts == 1)))
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
    two = counts[inv] == 2
    srt = np.flatnonzero(two)[np.argsort(inv[two], kind="stable")]
    fac2 = fac[srt].reshape(-1, 2)
    loc2 = loc[srt].reshape(-1, 2, nfv - 1)
    return uniq[counts == 2], fac2, loc2, np.unique(uniq[counts == 1])


def _components(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected-component label of ``n`` nodes joined by the edges ``(a, b)``."""
    graph = scipy.sparse.coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    return scipy.sparse.csgraph.connected_components(graph, directed=False)[1]


def crease_ridges(
    vid: np.ndarray,
    facet_normal: np.ndarray,
    ridge_facets: np.ndarray,
    ridge_vertices: np.ndarray,
    crease_angle: float,
) -> np.ndarray:
    """Which ridges are geometric creases (the rule in the module docstring).

    Args:
        vid: ``(F, nfv)`` vertex indices.
        facet_normal: ``(F, 3)`` unit outward facet normals.
        ridge_facets: ``(R, 2)``; ridge_vertices: ``(R, nfv - 1)`` (from ``_ridges``).
        crease_angle: degrees.

    Returns:
        ``(R,)`` bool.
    """
    big = np.radians(crease_angle)
    theta = _angle(facet_normal[ridge_facets[:, 0]], facet_normal[ridge_facets[:, 1]])
    crease = theta >= big
    cand = np.flatnonzero(~crease & (theta >= CREASE_FLOOR * big))
    if len(cand) == 0:
        return crease
    F, nfv = vid.shape
    vf = scipy.sparse.csr_matrix(
        (np.ones(F * nfv), (vid.ravel(), np.repeat(np.arange(F), nfv))), shape=(int(vid.max()) + 1, F)
    )
    pred = np.zeros((len(cand), 2))
    for s in (0, 1):  # the two sides of each ridge
        A = ridge_facets[cand, s]
        off = (vid[A][:, :, None] != ridge_vertices[cand][:, None, :]).all(axis=2)
        opposite = vid[A][np.arange(len(A)), np.argmax(off, axis=1)]
        fan, mask = padded_rows(vf, opposite)  # facets around the vertex opposite the ridge
        turn = _angle(facet_normal[fan], facet_normal[A][:, None, :])
        ok = mask & (fan != A[:, None]) & (turn < big)
        pred[:, s] = np.where(ok, turn, 0.0).max(axis=1, initial=0.0)
    crease[cand] = theta[cand] > CREASE_RATIO * pred.max(axis=1)
    return crease


def corner_normals(
    vid: np.ndarray,
    x: np.ndarray,
    facet_normal: np.ndarray,
    tag: np.ndarray,
    crease_angle: float = 60.0,
    split_tags: bool = True,
    scheme: str = "jet",
    allow_open: bool = False,
) -> CornerNormals:
    """Estimate one normal per smooth side at every boundary vertex.

    Args:
        vid: ``(F, nfv)`` vertex index of each facet corner (shared vertices equal).
        x: ``(F, nfv, 3)`` corner coordinates.
        facet_normal: ``(F, 3)`` unit outward facet normals.
        tag: ``(F,)`` facet tags.
        crease_angle: degrees, see :func:`crease_ridges`.
        split_tags: treat ridges between facets of different tags as creases.
        scheme: ``"jet"`` or a weighted mean (:data:`SCHEMES`).
        allow_open: accept an open surface (ridges of one facet); its boundary
            vertices get one-sided fits.

    Returns:
        :class:`CornerNormals`.
    """
    if scheme not in SCHEMES:
        raise ValueError(f"unknown normal estimate {scheme!r}; choose one of {list(SCHEMES)}")
    F, nfv = vid.shape
    rv, rf, rl, open_vertices = _ridges(vid, x, allow_open)
    geometric = crease_ridges(vid, facet_normal, rf, rv, crease_angle)
    crease = geometric | (tag[rf[:, 0]] != tag[rf[:, 1]]) if split_tags else geometric
    label = _sectors(rf, rl, ~crease, F, nfv)
    region = _components(F, rf[~crease, 0], rf[~crease, 1])
    w = corner_weights(x, "mwselr" if scheme == "jet" else scheme).ravel()
    sums = np.zeros((label.max() + 1, 3))
    np.add.at(sums, label.ravel(), w[:, None] * np.repeat(facet_normal, nfv, axis=0))
    norm = np.linalg.norm(sums, axis=1)
    if np.any(~(norm > 1e-300)):
        raise NormalsError(
            f"{np.count_nonzero(~(norm > 1e-300))} boundary vertices have a zero or NaN "
            "estimated normal (facets around them cancel out or are degenerate)"
        )
    mean = sums / norm[:, None]
    rings = None
    if scheme == "jet":
        per_vertex = np.bincount(np.unique(np.c_[vid.ravel(), label.ravel()], axis=0)[:, 0],
                                 minlength=int(vid.max()) + 1)
        sector_vertex = np.zeros(len(mean), dtype=np.int64)
        sector_vertex[label.ravel()] = vid.ravel()
        interior = (per_vertex[sector_vertex] == 1) & ~np.isin(sector_vertex, open_vertices)
        rings = SectorRings(vid, label, region)
        mean = fit_sector_normals(vid, x, label, region, mean, facet_normal, interior, rings)
    if split_tags and np.any(crease & ~geometric):
        mean = _tangent_tag_normals(mean, label, _sectors(rf, rl, ~geometric, F, nfv), region, facet_normal)
    return CornerNormals(mean[label], label, vid, rf, rv, crease, region, rings)


def _tangent_tag_normals(n: np.ndarray, label: np.ndarray, shared: np.ndarray, region: np.ndarray,
                         facet_normal: np.ndarray) -> np.ndarray:
    """One normal for the sectors of a vertex that only tags separate (a tangent CAD edge).

    ``n (S, 3)`` per sector of ``label (F, nfv)``; ``shared (F, nfv)`` joins
    the sectors across geometrically smooth ridges; ``region (F,)`` the
    smooth region (face) of each facet.  The sectors of a shared group get
    the normal of a member on a planar region (exact, and the blend is
    tangent to that plane there), else the mean of the members' normals,
    each estimated from its own face.
    """
    nfv = label.shape[1]
    lab, grp = label.ravel(), shared.ravel()
    S = len(n)
    ref = np.zeros((region.max() + 1, 3))
    ref[region] = facet_normal  # one facet normal per region
    flat = np.ones(len(ref), dtype=bool)
    np.logical_and.at(flat, region, np.einsum("fi,fi->f", facet_normal, ref[region]) >= 1.0 - 1e-14)
    planar = np.zeros(S, dtype=bool)
    planar[lab] = flat[np.repeat(region, nfv)]
    group = np.zeros(S, dtype=np.int64)
    group[lab] = grp
    total = np.zeros((grp.max() + 1, 3))
    np.add.at(total, group, n)
    plane = np.zeros_like(total)
    plane[group[planar]] = n[planar]  # any planar member (they lie in one plane)
    has_plane = np.zeros(len(total), dtype=bool)
    has_plane[group[planar]] = True
    out = np.where(has_plane[:, None], plane, total / np.linalg.norm(total, axis=1, keepdims=True))
    members = np.bincount(group, minlength=len(total))
    return np.where((members[group] > 1)[:, None], out[group], n)


def _sectors(rf: np.ndarray, rl: np.ndarray, smooth: np.ndarray, F: int, nfv: int) -> np.ndarray:
    """``(F, nfv)`` sector label of each corner: the corners of a vertex joined across ``smooth`` ridges."""
    sel = np.flatnonzero(smooth)
    a = (rf[sel, 0, None] * nfv + rl[sel, 0, :]).ravel()
    b = (rf[sel, 1, None] * nfv + rl[sel, 1, :]).ravel()
    return _components(F * nfv, a, b).reshape(F, nfv)
