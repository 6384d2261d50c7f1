"""Every converted face checked against OpenCASCADE when a file is read.

Our fast projection rests on our own representation of OpenCASCADE's faces
(:mod:`~nagata_snap.cad.surfaces`, :mod:`~nagata_snap.cad.nurbs`, trimming
polygons from the p-curves); a face converted wrongly would snap vertices
onto the wrong surface without a word.  So the reader (:mod:`nagata_snap.cad.read`,
where the OpenCASCADE shape exists) samples every face
(:func:`~nagata_snap.cad.read._checks`: a grid over its ``(u, v)`` box, 4 x 4, or 3 x 3
and 2 x 2 on OpenCASCADE's own analytic primitives and planes, which those fix; a point
on a p-curve of every wire and of a few more and two beside each, across the p-curve; the
placed instances of one face in an assembly share these samples, moved by their locations and
spot-checked against OpenCASCADE's own evaluation of each instance,
:func:`~nagata_snap.cad.read._placed_checks`), and :func:`check_faces` compares, on all
samples of all faces at once (every instance against its own conversion):

* **points** (on the face: the grid samples, those on the p-curves and those
  beside them that OpenCASCADE puts inside): our surface at OpenCASCADE's parameters (through the face's
  affine parameter map, where its description has one) within
  :data:`POINT_RTOL` of the model size of OpenCASCADE's point;
  (a face converted with ``BRepBuilderAPI_NurbsConvert``, whose parameters differ
  from the face's, is compared with OpenCASCADE's conversion, and the conversion's
  points must lie on the face's own surface within the same tolerance);
* **normals**: our outward unit normal (the face's orientation applied)
  within :data:`NORMAL_TOL` of OpenCASCADE's, where both are defined;
* **point-in-face**: our :class:`~nagata_snap.cad.trimming.TrimLoops` agree
  with ``BRepClass_FaceClassifier`` on every sample farther than a band from
  our loops (the band: a quarter of the distance of the points beside the
  p-curves, :data:`~nagata_snap.cad.read.CHECK_OFFSET` of the face's extent;
  OpenCASCADE's ``ON`` samples are not compared), and every sample on a
  p-curve is on our face (within its loops' band).

:func:`read_verified` reads a file and re-reads it while faces fail: a failed
face is described otherwise (``fallback``: first the surface it trims or
offsets, ``"basis"``; then OpenCASCADE's own NURBS conversion of the face,
``"nurbs"``; last a B-spline approximation of the surface to 1e-10 of the model size with
its parameters, ``"approx"``, for surfaces no NURBS reproduces, as an offset of a
B-spline surface) and checked again; a face that fails them all raises
:class:`~nagata_snap.cad.errors.CadError` naming it, its surface type and the
deviation found.  Never a silently wrong face.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from nagata_snap.cad.errors import CadError
from nagata_snap.cad.projection import evaluate_params, normalize_params
from nagata_snap.cad.topology import CadModel
from nagata_snap.mesh.arrays import Groups
from nagata_snap.mesh.simplex import cross

__all__ = ["FaceCheck", "check_faces", "read_verified", "POINT_RTOL", "NORMAL_TOL", "FALLBACKS"]

#: largest distance between our point and OpenCASCADE's, relative to the model size
POINT_RTOL = 1e-9
#: largest difference between our unit normal and OpenCASCADE's
NORMAL_TOL = 1e-6
#: the descriptions tried, in order, for a face that fails its check
FALLBACKS = ("basis", "nurbs", "approx")


@dataclass
class FaceCheck:
    """The check of one face against OpenCASCADE.

    Attributes:
        face: its index.
        point: largest point distance, relative to the model size.
        normal: largest unit-normal difference.
        mismatches: samples our point-in-face and OpenCASCADE's classifier disagree on.
        example: parameters ``(u, v)`` (OpenCASCADE's) of one disagreement, or None.
    """

    face: int
    point: float
    normal: float
    mismatches: int
    example: tuple[float, float] | None = None

    @property
    def ok(self) -> bool:
        """The face passed: points, normals and classification agree."""
        return self.point <= POINT_RTOL and self.normal <= NORMAL_TOL and self.mismatches == 0

    def deviation(self) -> str:
        """What failed, in words."""
        out = []
        if not self.point <= POINT_RTOL:
            out.append(f"points {self.point:.2e} of the model size off OpenCASCADE's")
        if not self.normal <= NORMAL_TOL:
            out.append(f"normals {self.normal:.2e} off")
        if self.mismatches:
            out.append(f"{self.mismatches} samples classified otherwise than by OpenCASCADE's face classifier "
                       f"(e.g. (u, v) = ({self.example[0]:.6g}, {self.example[1]:.6g}))" if self.example else "")
        return "; ".join(out)


def _samples(data: dict) -> tuple[np.ndarray, ...]:
    """All faces' OpenCASCADE samples concatenated: ``(face, uv, points, normals, state, kind,
    offset, gap)``, ``offset`` per sample (its face's), ``gap`` 0 but on converted faces; the
    outward unit normals (NaN where ``S_u x S_v`` vanishes) from the samples' derivatives and
    the faces' orientations, for all samples at once."""
    checks = [f["check"] for f in data["faces"]]
    n = np.array([len(c["uv"]) for c in checks], dtype=np.int64)
    face = np.repeat(np.arange(len(checks)), n)

    def cat(key: str, shape: tuple) -> np.ndarray:
        return np.concatenate([np.asarray(c[key]).reshape(-1, *shape) for c in checks] + [np.zeros((0, *shape))])

    offset = np.repeat(np.array([float(c["offset"]) for c in checks]), n)
    gap = np.concatenate([np.asarray(c.get("gap", np.zeros(len(c["uv"]))), dtype=float) for c in checks]
                         + [np.zeros(0)])
    D = cat("d1", (3, 3))
    N = np.stack(cross(list(D[:, 1].T), list(D[:, 2].T)), axis=1)  # (np.cross: the same numbers, slower)
    m = np.linalg.norm(N, axis=1)
    ok = (m > 1e-12 * np.linalg.norm(D[:, 1], axis=1) * np.linalg.norm(D[:, 2], axis=1)) & (m > 0)
    sign = np.where(np.array([bool(f["reversed"]) for f in data["faces"]] + [False]), -1.0, 1.0)[face]
    with np.errstate(invalid="ignore", divide="ignore"):
        N = np.where(ok[:, None], N * (sign / m)[:, None], np.nan)
    return (face, cat("uv", (2,)), np.ascontiguousarray(D[:, 0]), N, cat("state", ()).astype(np.int64),
            cat("kind", ()).astype(np.int64), offset, gap)


def _mapped(model: CadModel, face: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``(n, 2)``: OpenCASCADE's parameters ``uv`` of faces ``face`` as our surfaces' (the
    faces' affine maps ``[u, v, 1] M`` applied where they have one)."""
    out = uv.copy()
    maps = [f.uv_map for f in model.faces]
    has = np.array([M is not None for M in maps] + [False])[face]
    if has.any():
        M = np.stack([np.eye(3, 2) if M is None else np.asarray(M, dtype=float) for M in maps])[face[has]]
        out[has] = np.einsum("ni,nij->nj", np.c_[uv[has], np.ones(int(has.sum()))], M)
    return out


def _ours(model: CadModel, face: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, ...]:
    """Our points ``(n, 3)``, outward unit normals ``(n, 3)`` (NaN where undefined) and
    ``|S_u|, |S_v|`` ``(n,)`` of faces ``face`` at our parameters ``params (n, 2)``: the planes'
    all at once (their affine frames, :class:`~nagata_snap.cad.projection.AffineBatch`), the
    other analytic faces' all at once
    (:func:`~nagata_snap.cad.surfaces.revolution_tangents`), every other face by one
    evaluation of all its samples."""
    from nagata_snap.cad.projection import AffineBatch
    from nagata_snap.cad.surfaces import AnalyticSurface, revolution_tangents

    T = np.empty((len(face), 2, 3))
    P = np.empty((len(face), 3))
    surfaces = [f.surface for f in model.faces]
    aff = AffineBatch(surfaces)
    flat = aff.has[face]
    if flat.any():  # S(p) = origin + p @ axes (planes have no limits: nothing to wrap or clamp)
        e = face[flat]
        P[flat] = aff.origin[e] + np.einsum("nd,ndc->nc", params[flat], aff.axes[e])
        T[flat] = aff.axes[e]
    rev = np.array([isinstance(s, AnalyticSurface) for s in surfaces] + [False])[face] & ~flat
    if rev.any():
        r = np.flatnonzero(rev)
        P[r], T[r] = revolution_tangents(surfaces, face[r], _normalized(surfaces, face[r], params[r]))
    rows = np.flatnonzero(~flat & ~rev)
    g = Groups(face[rows])
    for i, sl in g:  # loop over the other faces (NURBS: each a different surface)
        r = rows[g.order[sl]]
        s = surfaces[i]
        P[r], T[r] = evaluate_params(s, normalize_params(s, params[r]), 1)
    n = np.stack(cross(list(T[:, 0].T), list(T[:, 1].T)), axis=1)
    m = np.linalg.norm(n, axis=1)
    su, sv = np.linalg.norm(T[:, 0], axis=1), np.linalg.norm(T[:, 1], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = np.where((m > 1e-12 * su * sv)[:, None] & (m > 0)[:, None], n / m[:, None], np.nan)
    flip = np.array([f.reversed for f in model.faces] + [False])[face]
    return P, np.where(flip[:, None], -n, n), su, sv


def _normalized(surfaces: list, face: np.ndarray, params: np.ndarray) -> np.ndarray:
    """``(n, 2)``: :func:`~nagata_snap.cad.projection.normalize_params` of the samples of
    ``surfaces[face]`` at ``params (n, 2)``, for all at once (the surfaces' bounds, periods and
    limits gathered per sample)."""
    from nagata_snap.cad.projection import entity_limits, entity_periods

    used = np.unique(face).tolist()
    lo = np.zeros((len(surfaces), 2))
    per = np.full((len(surfaces), 2), np.nan)
    lim = np.zeros((len(surfaces), 2, 2))
    for i in used:  # loop over the faces sampled (their domains)
        lo[i] = surfaces[i].bounds[:, 0]
        per[i] = entity_periods(surfaces[i])
        lim[i] = entity_limits(surfaces[i])
    lo, per, lim = lo[face], per[face], lim[face]
    p = np.array(params, dtype=float)
    wrap = np.isfinite(per)
    out = wrap & ((p < lo) | (p > lo + per))
    p[out] = lo[out] + np.mod(p[out] - lo[out], per[out])
    np.copyto(p, p.clip(lim[..., 0], lim[..., 1]), where=~wrap)
    return p


def check_faces(model: CadModel, data: dict) -> list[FaceCheck]:
    """Check every face of ``model`` against the OpenCASCADE samples of ``data`` (the reader's
    data the model was built from, read with ``check=True``); see the module docstring.

    Returns:
        per face its :class:`FaceCheck`.
    """
    face, uv, Pocc, Nocc, state, kind, offset, gap = _samples(data)
    nf = len(model.faces)
    params = _mapped(model, face, uv)
    P, N, su, sv = _ours(model, face, params)
    size = max(model.size, 1e-300)
    # (a face converted by OpenCASCADE is checked against its conversion, and the conversion
    # against the face's own surface: the gap)
    dp = (np.linalg.norm(P - Pocc, axis=1) + gap) / size
    dp = np.where(np.isfinite(dp), dp, np.inf)
    dn = np.linalg.norm(N - Nocc, axis=1)
    dn = np.where(np.isnan(dn), 0.0, dn)  # (where either normal is undefined)
    # points beside a p-curve and off the face may be off the surface's domain too (a
    # B-spline's knots), where OpenCASCADE extrapolates: they check the classification only
    off = (kind == 2) & (state != 0)
    dp[off] = 0.0
    dn[off] = 0.0
    bad = np.zeros(len(face), dtype=bool)
    trims = model.trim_loops()
    if trims is not None and len(face):
        # our polygons (even-odd) against the classifier, and every sample on a p-curve on
        # our face; the distance from our loops (less their band) is asked only where they
        # disagree: a sample on a p-curve outside our polygon must be within the band, any
        # other disagreement counts where the sample is farther than the band from our loops
        ins = trims.inside(face, params, band=False)
        on = kind == 1
        ask = np.flatnonzero((on & ~ins) | (~on & (state != 2) & (ins != (state == 0))))
        if ask.size:
            ld = trims.loop_distance(face[ask], params[ask], enough=0.0, scales=(su[ask], sv[ask]))
            bad[ask] = np.where(on[ask], ld > 0.0, ld > 0.25 * offset[ask])
    else:  # no face is trimmed: every sample is on its face
        bad = state == 1
    point = np.zeros(nf)
    normal = np.zeros(nf)
    np.maximum.at(point, face, dp)
    np.maximum.at(normal, face, dn)
    mism = np.bincount(face[bad], minlength=nf)
    first = {int(f): uv[k] for k, f in zip(np.flatnonzero(bad)[::-1], face[bad][::-1], strict=True)}
    return [FaceCheck(i, float(point[i]), float(normal[i]), int(mism[i]),
                      None if i not in first else (float(first[i][0]), float(first[i][1]))) for i in range(nf)]


def _kind(desc: dict) -> str:
    """A surface description's type in words (``"cylinder (from a SurfaceOfRevolution)"``)."""
    return desc["type"] if "source" not in desc else f"{desc['type']} (from a {desc['source']})"


def _failure(path: str, first: dict, c: FaceCheck) -> str:
    """The message of a face (first read as ``first``) that failed every description."""
    return (f"{path}: face {c.face} ({_kind(first)} surface) does not match OpenCASCADE's face, "
            f"neither as read nor re-read {', '.join(f'as its {k}' for k in FALLBACKS)}: {c.deviation()}; "
            "the file cannot be used safely (report it, or repair the face in a CAD system)")


def read_verified(path, *, unit: str = "MM", heal: bool = True, isolate: bool = True,
                  timeout: float | None = None, strict: bool = True) -> tuple[dict, CadModel]:
    """Read a CAD file, build its model and verify every face against OpenCASCADE.

    Faces that fail are re-read with the next description of :data:`FALLBACKS`
    (the file is read again, asking only those faces otherwise) until every
    face passes.

    Args:
        path, unit, heal, isolate, timeout: as :func:`~nagata_snap.cad.worker.read_cad`.
        strict: raise on a face that fails every description; ``False`` keeps it
            (counted as failed in ``model.verification``).

    Returns:
        ``(data, model)``: the reader's data (``data["verification"]`` the summary)
        and its model, whose ``verification`` is ``{"verified", "fell_back",
        "fallbacks" {description: faces}, "failed", "failed_faces", "worst_point",
        "worst_normal", "passes", "time"}`` (``time``: seconds of our side of the checks
        and of the re-reads and rebuilds for fallbacks; OpenCASCADE's samples of the first
        read are its ``times["check"]``; the model's trimming loops, which the checks use
        and the geometry built from the model reuses, are built before the clock starts).

    Raises:
        CadError: the file cannot be read (:func:`~nagata_snap.cad.worker.read_cad`),
            or (``strict``) a face fails every description: the message names it,
            its surface type and the deviation.
    """
    from nagata_snap.cad.worker import read_cad

    fallback: dict[int, str] = {}
    spent = 0.0
    passes = 0
    failed: dict[int, FaceCheck] = {}
    while True:
        tr = time.perf_counter()
        data = read_cad(path, unit=unit, heal=heal, isolate=isolate, timeout=timeout, fallback=fallback)
        t0 = time.perf_counter()
        if passes:  # a re-read for the fallbacks is the verification's cost
            spent += t0 - tr
        try:
            model = CadModel.from_data(data)
        except ValueError as e:
            msg = str(e)
            raise CadError(msg if data["path"] in msg else f"{data['path']}: {msg}") from None
        model.trim_loops()  # (the geometry's, built anyway: not the verification's cost)
        t1 = time.perf_counter()
        checks = check_faces(model, data)
        if not passes:
            first = [f["surface"] for f in data["faces"]]
        # our side: the checks, and the rebuilds of the model after the first
        spent += time.perf_counter() - (t0 if passes else t1)
        passes += 1
        todo: dict[int, str] = {}
        for c in checks:  # loop over the faces that failed (few)
            if c.ok or c.face in failed:
                continue
            used = data["faces"][c.face].get("fallback")  # (None: its first description)
            level = 0 if used is None else FALLBACKS.index(used) + 1
            if level >= len(FALLBACKS):
                if strict:
                    raise CadError(_failure(data["path"], first[c.face], c))
                failed[c.face] = c
                continue
            todo[c.face] = FALLBACKS[level]
        if not todo:
            break
        fallback.update(todo)
    used = [f.get("fallback") for f in data["faces"]]
    counts = {k: sum(u == k for u in used) for k in FALLBACKS}
    n_fb = sum(counts.values())
    v = {"verified": len(checks) - n_fb - len(failed), "fell_back": n_fb, "fallbacks": counts,
         "failed": len(failed), "failed_faces": sorted(failed),
         "worst_point": max((c.point for c in checks), default=0.0),
         "worst_normal": max((c.normal for c in checks), default=0.0), "passes": passes, "time": spent}
    model.verification = data["verification"] = v
    model.times["verify"] = spent
    for f in data["faces"]:  # (not needed further, e.g. not broadcast to the other ranks)
        f.pop("check", None)
    return data, model
