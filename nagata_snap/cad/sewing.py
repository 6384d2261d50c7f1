"""Sewing a faces-only shape on its walked data: vertices merged, edge copies joined.

Faces-only IGES files (type-144 trimmed surfaces, as gmsh and OpenCASCADE
write them) share no edge: every face has its own copy of each edge and
vertex.  OpenCASCADE's sewing (``BRepBuilderAPI_Sewing``), followed by
``ShapeFix_Solid::SolidFromShell`` on the closed shells and
``ShapeFix_Shape``, turns them into solids; it is general (it compares,
splits and re-parametrises edges, then fixes the whole shape) and costs
accordingly.  Where the faces meet cleanly, the same model follows from
plain data: :func:`nagata_snap.cad.read.read_shape` walks the unsewn
shape (faces in their order, every edge copy with its end vertices, a point
and the tangent at the middle of its range) and this module joins it,
vectorised (numpy, scipy), with no OpenCASCADE call:

* **vertices** within the sewing tolerance of each other (``rtol x`` the
  model size, the relative tolerances of OpenCASCADE's sewing tried in turn)
  become one, at their mean, with a tolerance covering every copy (its
  distance to the mean plus its own tolerance);
* **edges**: two copies are the same edge when their merged end vertices
  are the same pair and their middle points are within the tolerance (two
  half-circles between the same vertices do not match; a closed edge has
  one vertex twice).  A copy running the other way (by its vertices, or
  for a closed edge by its tangent) is *opposed*.  The copies must also
  meet at their quarter points (swapped where opposed): copies of one edge
  are parametrised alike or reversed.  The joined edge keeps one copy's 3D
  curve (a line or circle rather than a B-spline, else the first copy),
  with the largest tolerance of the copies and of the gap between them at
  those three points.  Degenerate edges (poles, apexes) stay with their
  face;
* **uses**: every face keeps its wires and p-curves (each use's p-curve is
  still parametrised along its own copy: ``opposed`` uses run against the
  joined edge's 3D curve); only the edge index changes, and a use is a
  seam when its face uses the joined edge twice (the two seam copies of a
  closed face);
* **shells and solids**: the faces connected through shared edges form a
  shell; every edge being used by exactly two faces (or twice by one, a
  seam) in opposite senses (a use's sense is OpenCASCADE's orientation of
  the edge in the face, which composes the face's own, against the joined
  curve where the use is opposed), it is closed and consistently
  oriented, and it becomes a solid, as ``SolidFromShell`` makes one.
  Which side is outside is decided by a supporting plane: a planar face
  whose plane has every face of its shell on one side (within the
  tolerance), tested with OpenCASCADE's bounding box of each face (for a
  plane the box of its edges, else of the surface over the face's
  ``(u, v)`` box, enlarged by the tolerance: it encloses the face).  The
  solid lies on that side, so the face's oriented normal points outward
  exactly when it points away from it.  ``SolidFromShell`` reverses a shell
  its classifier finds inward.

The join is used only where every copy pairs without ambiguity and the
shells close, consistently and outward oriented: there OpenCASCADE's
sewing makes the same model (the tests compare the two part by part).
Anything else returns the reason, and the caller sews with OpenCASCADE
instead: a vertex cluster wider than the tolerance or another
cluster within twice the tolerance (a chain, or near misses: ambiguous), an
edge that collapses into a vertex, an edge without vertices or 3D curve, a
copy with no partner (a free edge: an open shell) or with more than one
(more than two faces on an edge), copies whose directions disagree or that
do not meet at their quarter points, a
joined edge not used exactly twice, two uses in the same sense
(inconsistent orientation), a shell whose outside no planar face decides,
and a shell oriented inward (OpenCASCADE would reverse it; its faces'
wires would then be walked backwards, which is left to OpenCASCADE).

What differs from OpenCASCADE's sewn shape, and why it does not matter
downstream: the faces keep the unsewn order (OpenCASCADE orders them shell
by shell), the kept 3D curve may be another copy of the edge (all copies
lie within the tolerance), the merged vertex is the mean of its copies
(OpenCASCADE places it a little differently, within the tolerance), edge
and vertex tolerances are not re-measured along the curves as
OpenCASCADE does, and p-curves keep their own
parametrisation (OpenCASCADE re-parametrises them along the kept curve; the
trimming loops sample them as curves in the ``(u, v)`` plane, whatever the
parameter).  Each joined edge records its ``source``: the copy whose 3D curve
it keeps, so that a reference built from the unsewn shape (the test's
OpenCASCADE distances) is numbered as the model.

The arrays are small (tens to hundreds of vertices and edges), so the cost is
numpy's per-call overhead: rows are gathered with ``take`` and selected with
``compress`` (cheaper calls than fancy indexing), and what only names a
failure (which shell is inward, whether planes disagree) is worked out
where the test fails.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["EdgeCopies", "FaceUses", "Joined", "join_edges", "join_faces", "relabel", "TANGENT_COS"]

#: copies of an edge must have parallel (or antiparallel) tangents at their middle points:
#: ``|cos|`` of their angle at least this
TANGENT_COS = 0.9


@dataclass
class EdgeCopies:
    """The vertices and edges of an unsewn shape (as OpenCASCADE numbers them).

    Attributes:
        points: ``(nv, 3)`` vertex points (length units).
        vertex_tolerance: ``(nv,)`` their tolerances (length units).
        ends: ``(ne, 2)`` first and last vertex of each edge (``-1``: none).
        tolerance: ``(ne,)`` edge tolerances (length units).
        degenerate: ``(ne,)`` degenerate edges (a pole or an apex: no 3D curve).
        curved: ``(ne,)`` edges whose 3D curve is neither a line nor a circle (kept only
            where no copy is one).
        mid: ``(ne, 3)`` the point at the middle of each edge's parameter range (NaN for
            degenerate edges and edges without a 3D curve).
        tangent: ``(ne, 3)`` the curve's derivative there (any length; NaN likewise).
        quarters: ``(ne, 2, 3)`` the points at a quarter and three quarters of the range
            (NaN likewise).
    """

    points: np.ndarray
    vertex_tolerance: np.ndarray
    ends: np.ndarray
    tolerance: np.ndarray
    degenerate: np.ndarray
    curved: np.ndarray
    mid: np.ndarray
    tangent: np.ndarray
    quarters: np.ndarray


@dataclass
class FaceUses:
    """The wires of the unsewn faces, as edge uses, and what decides their outside.

    Attributes:
        face: ``(nu,)`` face of each edge use (every wire of every face, in order).
        edge: ``(nu,)`` the (unsewn) edge used.
        reversed: ``(nu,)`` the use's orientation in the face, composed with the face's
            own (OpenCASCADE's edge orientation as the face's wires are explored).
        num_faces: number of faces.
        plane: ``(nf,)`` planar faces (with a plane of their own, whose normal is known).
        origin: ``(nf, 3)`` a point of each planar face's plane (any for other faces).
        normal: ``(nf, 3)`` the planar faces' oriented normals (``S_u x S_v``, negated
            for a reversed face: outward if the shell is oriented outward).
        box: ``(nf, 2, 3)`` lower and upper corner of every face's bounding box (NaN: none).
    """

    face: np.ndarray
    edge: np.ndarray
    reversed: np.ndarray
    num_faces: int
    plane: np.ndarray
    origin: np.ndarray
    normal: np.ndarray
    box: np.ndarray


@dataclass
class Joined:
    """The sewn shape, as a renumbering of the unsewn one (see the module docstring).

    Attributes:
        tolerance: the sewing tolerance used (length units).
        vertex: ``(nv_src,)`` merged vertex of every unsewn vertex.
        points: ``(nv, 3)`` merged vertices (the mean of their copies).
        vertex_tolerance: ``(nv,)`` their tolerances.
        edge: ``(ne_src,)`` joined edge of every unsewn edge (numbered by their first copy).
        source: ``(ne,)`` the unsewn edge whose 3D curve each joined edge keeps.
        ends: ``(ne, 2)`` merged end vertices of each joined edge (its kept copy's).
        edge_tolerance: ``(ne,)`` tolerance of each joined edge.
        opposed: ``(ne_src,)`` unsewn edges that run against their joined edge's 3D curve.
        seam: ``(nu,)`` edge uses (not degenerate) whose face uses their joined edge twice
            (set by :func:`join_faces`).
        shell: ``(nf,)`` shell (and solid) of every face (set by :func:`join_faces`).
        num_solids: number of shells, all closed and made solids.
    """

    tolerance: float
    vertex: np.ndarray
    points: np.ndarray
    vertex_tolerance: np.ndarray
    edge: np.ndarray
    source: np.ndarray
    ends: np.ndarray
    edge_tolerance: np.ndarray
    opposed: np.ndarray
    seam: np.ndarray | None = None
    shell: np.ndarray | None = None
    num_solids: int = 0


def _length(d: np.ndarray) -> np.ndarray:
    """Euclidean lengths of the vectors along the last axis of ``d`` (``(..., 3)`` -> ``(...)``,
    length units): ``np.linalg.norm(d, axis=-1)`` to the last bit, without its dispatch (the
    arrays here are small: the calls' overhead is their cost)."""
    return np.sqrt((d * d).sum(axis=-1))


def _components(n: int, pairs: np.ndarray) -> np.ndarray:
    """``(n,)`` component label of each of ``n`` nodes joined by ``pairs (k, 2)``, numbered
    in the order of their lowest node.

    Every node takes the lowest label among its neighbours' and its own, then the label of
    its label (pointer jumping), until the two nodes of every pair have the same label: a
    few passes over the pairs (one where they pair the nodes off; the graphs here are
    small: vertex clusters, edge copies, faces).  A pair of a node with itself is allowed
    (it joins nothing).
    """
    ids = np.arange(n)
    if len(pairs) == 0:
        return ids
    src, dst = pairs.ravel(), pairs[:, ::-1].ravel()  # every pair both ways
    lab = ids.copy()
    while True:  # a few passes (until the labels are settled)
        np.minimum.at(lab, src, lab[dst])
        lab = lab[lab]
        if (lab[src] == lab[dst]).all():
            break
    # settled: a node's label is a node of its component, none above the node, and the same
    # for the whole component: its lowest node (labelled itself), numbered in their order
    roots = (lab == ids).nonzero()[0]
    ids[roots] = np.arange(len(roots))
    return ids[lab]


def _merge_vertices(P: np.ndarray, vtol: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray,
                                                                       np.ndarray] | str:
    """Vertices of ``P (nv, 3)`` within ``tol`` of each other, merged.

    Returns:
        ``(label (nv,), points (m, 3), tolerance (m,))``, or why the clusters are
        ambiguous: one wider than ``tol`` (a chain), or two within ``2 tol``.
    """
    n = len(P)
    near = cKDTree(P).query_pairs(2.0 * tol, output_type="ndarray")
    a, b = near[:, 0], near[:, 1]
    lab = _components(n, near.compress(_length(P.take(a, 0) - P.take(b, 0)) <= tol, 0))
    m = int(lab.max()) + 1 if n else 0
    box = np.full((m, 6), np.inf)  # every cluster's lower corner and upper corner negated
    np.minimum.at(box, lab, np.concatenate((P, -P), axis=1))
    wide = np.count_nonzero(_length(-box[:, 3:] - box[:, :3]) > tol)
    if wide:
        return f"{wide} vertex clusters wider than the tolerance (chained vertices)"
    if (lab[a] != lab[b]).any():
        return "vertices of different clusters within twice the tolerance"
    mean = np.zeros((m, 3))
    np.add.at(mean, lab, P)
    mean /= np.bincount(lab, minlength=m)[:, None]
    vt = np.zeros(m)
    np.maximum.at(vt, lab, _length(P - mean.take(lab, 0)) + vtol)
    return lab, mean, vt


def join_edges(w: EdgeCopies, tol: float) -> Joined | str:
    """Merge the vertices and pair the edge copies of an unsewn shape at tolerance ``tol``.

    Every non-degenerate edge must find exactly one other copy (the same merged
    end vertices, middle and quarter points within ``tol``); degenerate edges
    stay alone.

    Returns:
        the :class:`Joined` vertices and edges (faces not yet checked: see
        :func:`join_faces`), or why the edges do not join cleanly.
    """
    merged = _merge_vertices(w.points, w.vertex_tolerance, tol)
    if isinstance(merged, str):
        return merged
    vlab, points, vtol = merged
    ne = len(w.ends)
    curve = ~w.degenerate
    nd = curve.nonzero()[0]
    if not np.isfinite(w.mid.take(nd, 0)).all():
        return "an edge without a 3D curve"
    if (w.ends < 0).any():
        return "an edge without vertices"
    ends = vlab[w.ends]
    first = ends[:, 0]
    closed = first == ends[:, 1]
    if (curve & closed & (_length(w.mid - points.take(first, 0)) <= tol)).any():
        return "an edge shorter than the tolerance (its vertices merge)"
    # copies: same merged end vertices (either order), middle points within tol; candidates:
    # the pairs of copies with the same vertices (runs of the copies sorted by them)
    key = ends.take(nd, 0)
    key.sort(axis=1)
    key = key[:, 0] * len(points) + key[:, 1]
    srt = key.argsort(kind="stable")
    order, key = nd[srt], key[srt]
    runs = []
    for s in range(1, len(key)):  # pairs s apart in a run (runs are short: a pass per run length)
        i = (key[s:] == key[:-s]).nonzero()[0]
        if len(i) == 0:
            break
        runs.append(order[i[:, None] + (0, s)])
    cand = np.concatenate(runs) if runs else np.zeros((0, 2), dtype=np.int64)
    d = _length(w.mid.take(cand[:, 0], 0) - w.mid.take(cand[:, 1], 0))
    near = cand.compress(d <= 2.0 * tol, 0)
    a, b = near[:, 0], near[:, 1]
    lab = _components(ne, cand.compress(d <= tol, 0))
    size = np.bincount(lab)
    more = np.count_nonzero(size > 2)
    if more:
        return f"{more} edges with more than two copies (more than two faces)"
    single = np.count_nonzero(curve & (size[lab] == 1))
    if single:
        return f"{single} free edges (an open shell)"
    if (lab[a] != lab[b]).any():
        return "copies of different edges within twice the tolerance"
    # the kept copy: a line or circle rather than another curve, else the first
    m = len(size)
    best = np.full(m, 2 * ne + 1)
    np.minimum.at(best, lab, w.curved * ne + np.arange(ne))
    source = best % ne
    keep = source[lab]
    # directions of the copies against the kept one: by their vertices, or (closed edges)
    # by their tangents, which must agree in any case
    t, nt = w.tangent, _length(w.tangent)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = (t * t.take(keep, 0)).sum(axis=1) / (nt * nt[keep])
    opposed = np.where(closed[keep], cos < 0, first != first[keep])
    if (curve & ~(np.where(opposed, -cos, cos) >= TANGENT_COS)).any():
        return "copies of an edge whose directions disagree"
    # the gap between copies: at their middle and quarter points (an opposed copy's quarters
    # swapped), which must correspond (copies parametrised alike, or reversed)
    q = w.quarters.take(keep, 0)
    q = np.where(opposed[:, None, None], q[:, ::-1], q)
    gap = np.maximum(_length(w.mid - w.mid.take(keep, 0)), _length(w.quarters - q).max(axis=1))
    if (curve & ~(gap <= tol)).any():
        return "copies of an edge that differ away from their middle points (parametrised differently)"
    etol = np.zeros(m)
    np.maximum.at(etol, lab, np.maximum(w.tolerance, np.where(curve, gap, 0.0)))
    return Joined(tol, vlab, points, vtol, lab, source, ends.take(source, 0), etol, opposed & curve)


def join_faces(j: Joined, u: FaceUses, curve: np.ndarray) -> Joined | str:
    """Check the faces' uses of the joined edges and make the shells, closed and outward.

    Args:
        j: :func:`join_edges`'s result (completed here: ``seam``, ``shell``, ``num_solids``).
        u: the faces' edge uses and what decides their outside.
        curve: ``(ne_src,)`` the unsewn edges that are not degenerate.

    Returns:
        ``j`` completed, or why the faces do not make closed, consistently and
        outward oriented shells.
    """
    nf = u.num_faces
    if np.count_nonzero(np.bincount(u.face, minlength=nf)) < nf:
        return "a face without edges"
    m = j.edge[u.edge]
    sense = u.reversed ^ j.opposed[u.edge]  # against the joined edge's 3D curve
    shared = curve[u.edge].nonzero()[0]
    ms = m[shared]
    if (np.bincount(ms, minlength=len(j.source))[curve[j.source]] != 2).any():
        return "a joined edge not used exactly twice"
    pairs = shared[ms.argsort(kind="stable")].reshape(-1, 2)  # the two uses of each joined edge
    same = np.count_nonzero(sense[pairs[:, 0]] == sense[pairs[:, 1]])
    if same:
        return f"{same} edges used twice in the same sense (inconsistent orientation)"
    faces = u.face[pairs]
    seam = np.zeros(len(m), dtype=bool)
    seam[pairs.compress(faces[:, 0] == faces[:, 1], 0)] = True
    shell = _components(nf, faces)  # (a seam's pair joins its face to itself)
    side = _outside(u, shell, j.tolerance)
    if isinstance(side, str):
        return side
    j.seam, j.shell, j.num_solids = seam, shell, int(shell.max()) + 1
    return j


def _outside(u: FaceUses, shell: np.ndarray, tol: float) -> str | None:
    """None if every shell is oriented outward; else why not (inward, or undecided).

    A planar face decides its shell when the bounding boxes of all the
    shell's faces lie on one side of its plane (within ``tol``): outward if
    on the side its oriented normal points away from.  Every deciding face
    must agree.
    """
    if not np.isfinite(u.box).all():
        return "a face without a bounding box"
    lo, hi = u.box[:, 0], u.box[:, 1]
    c, h = (lo + hi) * 0.5, 0.5 * (hi - lo)
    p = u.plane.nonzero()[0]
    n = u.normal.take(p, 0)
    n = n / _length(n)[:, None]
    # (np, nf): the extent of every face's box along each plane's normal, from the plane
    centre = n @ c.T - (n * u.origin.take(p, 0)).sum(axis=1)[:, None]
    reach = np.abs(n) @ h.T
    sp = shell[p]
    other = sp[:, None] != shell
    below = (other | (centre + reach <= tol)).all(axis=1)   # all on the side -n: outward
    above = (other | (centre - reach >= -tol)).all(axis=1)  # all on the side +n: inward
    ns = int(shell.max()) + 1
    out = np.bincount(sp[below & ~above], minlength=ns)
    inward = above & ~below
    if inward.any():  # (then which: planes that disagree, or an inward shell)
        inw = np.bincount(sp[inward], minlength=ns)
        if ((out > 0) & (inw > 0)).any():
            return "planar faces disagree on which side of a shell is outside"
        return f"shell {int(np.argmax(inw > 0))} is oriented inward (OpenCASCADE reverses it)"
    if (out == 0).any():
        return f"no planar face decides which side of shell {int(np.argmin(out > 0))} is outside"
    return None


def relabel(faces: list[dict[str, Any]], j: Joined) -> None:
    """Renumber the walked faces' edge uses (in place) to the joined edges.

    ``faces``: :func:`~nagata_snap.cad.read.read_shape`'s face descriptions of the
    unsewn shape, whose uses (every wire of every face, in order) are those of the
    :class:`FaceUses` given to :func:`join_faces`.  Each use gets its joined
    ``edge``, ``seam`` and ``opposed``; each face its ``solids``.
    """
    assert j.seam is not None and j.shell is not None
    k = 0
    edge, opposed, seam = j.edge.tolist(), j.opposed.tolist(), j.seam.tolist()
    for f, s in zip(faces, j.shell.tolist(), strict=True):  # loop over faces and their uses
        f["solids"] = [s]
        for w in f["wires"]:
            for use in w["uses"]:
                e = use["edge"]
                use["edge"], use["opposed"] = edge[e], opposed[e]
                if not use["degenerate"]:
                    use["seam"] = seam[k]
                k += 1
