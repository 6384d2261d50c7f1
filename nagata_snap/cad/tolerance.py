"""Where a file's faces meet only within its tolerances: how far a point may be from its face.

A STEP or IGES file is written with a tolerance: OpenCASCADE gives every edge
and vertex its own (``BRep_Tool::Tolerance``, kept in :class:`~nagata_snap.cad.topology.Edge`'s
``tolerance`` and :attr:`CadModel.vertex_tolerance <nagata_snap.cad.topology.CadModel>`)
and takes a point within that distance of an edge (its *tolerance tube*) to be
on the edge.  Two faces that share an edge therefore meet only within its
tolerance: at a corner of a CATIA file the vertex can be 4.5e-5 mm off one of
its faces while OpenCASCADE calls the shape valid.  A snapped boundary vertex on
such an edge, placed on one face, is that far from the other one, and a
distance report that counts it as off its face cries wolf.

:func:`tolerance_gaps` gives each point the distance the file itself allows:
the largest tolerance of an edge of its face (or of a vertex of those edges)
whose tube holds the point, else ``rtol`` of the model size;
:func:`meeting_gaps` adds where the faces' surfaces meet.  An edge within its
tolerance ``t`` of both its faces does not put the faces' intersection within
``t`` of the edge: two surfaces each known to ``t`` and meeting at an angle
``theta`` cross anywhere within ``t / sin(theta / 2)`` of the edge (in the plane
across the edge, the point at distances ``a, b <= t`` from two lines at angle
``theta`` is ``sqrt(a^2 + b^2 + 2 a b cos theta) / sin theta <= t / sin(theta / 2)``
from their crossing).  Placement puts a vertex of an edge onto that
intersection (:func:`~nagata_snap.cad.features.intersect`; not where the faces
are tangent within :data:`~nagata_snap.cad.features.TANGENT_RCOND`, which bounds
the angle here), so on a file whose edges lie off their faces by nearly their
tolerance (the CATIA V5 bolt, the ST-Developer sheet of the corpus) a snapped
vertex on both faces' surfaces can be a little beyond the edge's tube, and
beyond the trimmed face by as much;
:func:`count_far` counts the points farther than ``rtol`` of the size from their
face and those of them the file's tolerances explain.  The CLI's summary
(:func:`nagata_snap.cli.boundary_far`) and ``benchmarks/cad_corpus.py`` both use it.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from nagata_snap.cad.features import TANGENT_RCOND
from nagata_snap.cad.params import unit_normals
from nagata_snap.cad.projection import GlobalSearcher, evaluate_params, normalize_params, project_points
from nagata_snap.cad.topology import CadModel
from nagata_snap.mesh.arrays import Ragged

__all__ = ["FAR_RTOL", "tolerance_gaps", "meeting_gaps", "count_far"]

#: a point farther than this from its face, relative to the model size, is reported
FAR_RTOL = 1e-9
#: samples of an edge curve's range whose nearest seeds the projection onto it
SEED_SAMPLES = 33


def _curve_distance(curve, X: np.ndarray) -> np.ndarray:
    """``(m,)`` distance of ``X (m, 3)`` from the (bounded) 3D curve of an edge (length units):
    closed form for lines and circles, else Newton from the nearest of
    :data:`SEED_SAMPLES` samples of its range."""
    t0, t1 = curve.bounds[0]
    t = normalize_params(curve, np.linspace(t0, t1, SEED_SAMPLES)[:, None])
    S = evaluate_params(curve, t, 0)
    t = t[:, 0]
    seeds = t[np.argmin(np.linalg.norm(X[:, None, :] - S[None], axis=2), axis=1)]
    res = project_points(curve, X, seeds[:, None])
    return np.asarray(res.distance, dtype=float)


def tolerance_gaps(model: CadModel, faces: npt.ArrayLike, points: npt.ArrayLike,
                   rtol: float = FAR_RTOL, meet: bool = False) -> np.ndarray:
    """How far each point may be from its face because the file's faces meet only within
    the file's tolerances.

    Args:
        model: the CAD model (its edges' and vertices' tolerances).
        faces: ``(n,)`` the face of each point (index into ``model.faces``).
        points: ``(n, 3)`` the points (length units of the model).
        rtol: the distance allowed anywhere, relative to ``model.size``.
        meet: also where the faces' surfaces meet (:func:`meeting_gaps`).

    Returns:
        ``(n,)`` (length units): the largest tolerance of an edge of the point's face, or of
        a vertex of those edges, whose tolerance tube (radius the tolerance, at least
        ``rtol`` of the size) holds the point (with ``meet``, or :func:`meeting_gaps`'
        radius, if larger); ``rtol`` of the size where none does.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1)
    X = np.asarray(points, dtype=float).reshape(len(faces), 3)
    floor = rtol * model.size
    gap = np.full(len(faces), floor)
    if len(faces) == 0:
        return gap
    pt, edge = _edge_pairs(model, faces)  # (point, edge) pairs
    etol = np.array([e.tolerance for e in model.edges] + [0.0])
    d = _edge_distances(model, edge, X[pt])
    inside = d <= np.maximum(etol[edge], floor)
    np.maximum.at(gap, pt[inside], etol[edge[inside]])
    # (point, vertex) pairs: the end vertices of those edges
    ends = np.array([e.vertices for e in model.edges], dtype=np.int64).reshape(-1, 2)
    vp, vv = np.repeat(pt, 2), ends[edge].reshape(-1)
    ok = vv >= 0
    vp, vv = vp[ok], vv[ok]
    vtol = model.vertex_tolerance[vv]
    inside = np.linalg.norm(X[vp] - model.vertices[vv], axis=1) <= np.maximum(vtol, floor)
    np.maximum.at(gap, vp[inside], vtol[inside])
    return np.maximum(gap, meeting_gaps(model, faces, X, rtol)) if meet else gap


def _edge_distances(model: CadModel, edge: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """``(k,)`` distance of ``Y (k, 3)`` from the curve of edge ``edge[i]`` (:func:`_curve_distance`)."""
    d = np.empty(len(edge))
    order = np.argsort(edge, kind="stable")
    cut = np.flatnonzero(np.diff(edge[order])) + 1
    for rows in np.split(order, cut) if len(order) else []:  # loop over the edges concerned
        d[rows] = _curve_distance(model.edges[int(edge[rows[0]])].curve, Y[rows])
    return d


def _edge_pairs(model: CadModel, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(point (k,), edge (k,))``: every edge with a curve bounding the face ``faces[i]`` of each point."""
    n, edge = Ragged([f.edges for f in model.faces]).take(faces)
    return np.repeat(np.arange(len(faces)), n), edge


def meeting_gaps(model: CadModel, faces: npt.ArrayLike, points: npt.ArrayLike,
                 rtol: float = FAR_RTOL) -> np.ndarray:
    """How far each point may be from its face because the faces' surfaces meet only within
    the file's edge tolerances of an edge (see the module docstring).

    Args:
        model, faces, points, rtol: as :func:`tolerance_gaps`.

    Returns:
        ``(n,)`` (length units): the largest ``t / sin(theta / 2)`` of an edge of the point's
        face with two faces whose surfaces both hold the point (within ``rtol`` of the size),
        ``t`` the edge's tolerance and ``theta`` the angle of the faces' normals at the
        point (not below the tangent limit of the placement), where the point is within it
        of the edge's curve; ``rtol`` of the size where no edge has.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1)
    X = np.asarray(points, dtype=float).reshape(len(faces), 3)
    floor = rtol * model.size
    gap = np.full(len(faces), floor)
    pt, edge = _edge_pairs(model, faces)
    two = np.array([len(e.faces) == 2 for e in model.edges] + [False])
    pt, edge = pt[two[edge]], edge[two[edge]]
    if len(pt) == 0:
        return gap
    ef = np.array([e.faces if len(e.faces) == 2 else (0, 0) for e in model.edges], dtype=np.int64)[edge]
    # the point on both faces' surfaces: closest points on each, from the surfaces' search samples
    searcher = GlobalSearcher([f.surface for f in model.faces])
    par, _, dist = searcher.search_on(np.repeat(X[pt], 2, axis=0), ef.reshape(-1))[:3]
    on = np.all(dist.reshape(-1, 2) <= floor, axis=1)
    N = unit_normals([f.surface for f in model.faces], ef.reshape(-1), par).reshape(-1, 2, 3)
    cos = np.clip(np.abs(np.einsum("ij,ij->i", N[:, 0], N[:, 1])), 0.0, 1.0)
    # tan(theta / 2) = sqrt((1 - cos) / (1 + cos)): the placement's tangent limit
    half = np.sqrt((1.0 - cos) / 2.0)  # sin(theta / 2)
    ok = on & (np.sqrt((1.0 - cos) / (1.0 + cos)) >= TANGENT_RCOND)
    etol = np.array([e.tolerance for e in model.edges])[edge]
    r = np.where(ok, etol / np.maximum(half, 1e-300), 0.0)
    rows = np.flatnonzero(ok & (r > floor))
    d = np.full(len(pt), np.inf)
    d[rows] = _edge_distances(model, edge[rows], X[pt[rows]])
    inside = d <= r
    np.maximum.at(gap, pt[inside], r[inside])
    return gap


def count_far(model: CadModel | None, faces: npt.ArrayLike, points: npt.ArrayLike, dist: npt.ArrayLike,
              size: float, rtol: float = FAR_RTOL, meet: bool = False) -> tuple[int, int]:
    """The points farther than ``rtol`` of the size from their face, and how many of them
    the file's own tolerances explain.

    Args:
        model: the CAD model, or None (no tolerances known: none is explained).
        faces, points: as :func:`tolerance_gaps`.
        dist: ``(n,)`` each point's distance from its face (length units).
        size: the model size (length units).
        rtol, meet: as :func:`tolerance_gaps`.

    Returns:
        ``(far, within)``: points with ``dist > rtol * size``, and of them those within
        the gap :func:`tolerance_gaps` allows them (inside the tolerance tube of an edge
        or vertex of their face, and no farther from it than that tolerance; with
        ``meet``, or where the faces' surfaces meet within the edge's tolerance).
    """
    dist = np.asarray(dist, dtype=float).reshape(-1)
    far = np.flatnonzero(dist > rtol * size)
    if model is None or far.size == 0:
        return int(far.size), 0
    faces = np.asarray(faces, dtype=np.int64).reshape(-1)[far]
    X = np.asarray(points, dtype=float).reshape(-1, 3)[far]
    gap = tolerance_gaps(model, faces, X, rtol, meet)
    return int(far.size), int(np.count_nonzero(dist[far] <= gap))
