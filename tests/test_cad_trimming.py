"""Point-in-face of nagata_snap.cad.trimming against OpenCASCADE's face classifier.

Parts built with gmsh's OpenCASCADE and written as STEP (planes with round
holes, filleted edges, cylinders, a sphere, a cone with its apex, a torus:
seams, poles and an apex) are read by :meth:`CadGeometry.from_file`.  On every
face, parameter points are classified by :class:`TrimLoops` and by
``BRepClass_FaceClassifier`` on OCC's own face: random points of the face's
``(u, v)`` box, and points a small distance inside and outside every loop
segment (near seams, poles, holes and corners).  Away from the boundary band
the answers must agree exactly; points shifted by a period in a closed
direction must get the same answer as the point itself.
"""

from __future__ import annotations

import gmsh
import numpy as np
import pytest

from nagata_snap.cad import CadGeometry
from nagata_snap.cad.projection import entity_limits, entity_periods, evaluate_params, normalize_params

from occ_reference import OccShape

from OCP.BRepClass import BRepClass_FaceClassifier
from OCP.TopAbs import TopAbs_State
from OCP.gp import gp_Pnt2d

RNG = np.random.default_rng(3)


def build(kind: str, path: str) -> None:
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        occ = gmsh.model.occ
        if kind == "plate":
            b = occ.addBox(0, 0, 0, 2, 1, 0.4)
            holes = [(3, occ.addCylinder(x, 0.5, -1, 0, 0, 3, r)) for x, r in ((0.5, 0.2), (1.4, 0.25))]
            out, _ = occ.cut([(3, b)], holes)
            occ.synchronize()
            occ.fillet([out[0][1]], [1, 3, 5], [0.08])
        else:
            occ.addSphere(0, 0, 0, 0.5)
            occ.addCone(2, 0, 0, 0, 0, 1, 0.5, 0)
            occ.addTorus(4, 0, 0, 0.8, 0.25)
            occ.addCylinder(6, 0, 0, 0, 0, 1, 0.4)
        occ.synchronize()
        gmsh.write(path)
    finally:
        gmsh.finalize()


@pytest.fixture(scope="module", params=["plate", "revolved"])
def part(request, tmp_path_factory):
    path = str(tmp_path_factory.mktemp("trim") / f"{request.param}.step")
    build(request.param, path)
    return CadGeometry.from_file(path), OccShape(path)


def occ_inside(face, uv: np.ndarray) -> np.ndarray:
    out = np.empty(len(uv), dtype=bool)
    for i, (u, v) in enumerate(uv):
        st = BRepClass_FaceClassifier(face, gp_Pnt2d(float(u), float(v)), 1e-9).State()
        out[i] = st == TopAbs_State.TopAbs_IN
    return out


def metric(surface, q):
    """``(k, 2)``: ``|S_u|, |S_v|`` at parameters ``q`` (length per parameter unit)."""
    _, T = evaluate_params(surface, normalize_params(surface, q), 1)
    return np.linalg.norm(T, axis=2)


def seg_distance(loops, q, scale):
    """Distance (length units, through ``scale = (|S_u|, |S_v|)`` at ``q``) to the nearest segment."""
    d = np.full(len(q), np.inf)
    for P in loops:
        a, b = P[None] * scale[:, None], np.roll(P, -1, axis=0)[None] * scale[:, None]
        qq = q[:, None] * scale[:, None]
        ab = b - a
        t = np.clip(np.einsum("qkj,qkj->qk", qq - a, ab) / np.maximum((ab**2).sum(-1), 1e-300), 0, 1)
        r = qq - a - t[..., None] * ab
        d = np.minimum(d, np.sqrt((r**2).sum(-1)).min(axis=1))
    return d


def test_point_in_face_matches_occ_classifier(part):
    geo, occ = part
    assert geo.num_entities == len(occ.faces)
    checked = n_in = 0
    for e, face in enumerate(geo.model.faces):
        surf = face.surface
        loops = [lp.points for lp in face.loops]
        band = max(lp.band.max() for lp in face.loops)
        delta = 4 * band + 1e-4 * geo.size  # length units: well clear of the band
        box = np.array([np.concatenate(loops).min(axis=0), np.concatenate(loops).max(axis=0)])
        span = np.maximum(box[1] - box[0], 1e-9)
        q = [box[0] - 0.05 * span + RNG.random((300, 2)) * 1.1 * span]
        for P in loops:  # a little inside and outside every segment, at its middle and ends
            a, b = P, np.roll(P, -1, axis=0)
            nrm = np.stack([b[:, 1] - a[:, 1], a[:, 0] - b[:, 0]], axis=1)
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
            for t in (0.5, 0.1, 0.9):
                m = a + t * (b - a)
                step = delta / np.maximum(np.linalg.norm(nrm * metric(surf, m), axis=1), 1e-300)
                q += [m + step[:, None] * nrm, m - step[:, None] * nrm]
        q = np.concatenate(q)
        lim = entity_limits(surf)
        q = q[np.all((q >= lim[:, 0]) & (q <= lim[:, 1]), axis=1)]  # e.g. not beyond a pole
        q = q[seg_distance(loops, q, metric(surf, q)) >= 0.5 * delta]  # clear of the band
        # OCC's classifier does not wrap: ask it at the parameter inside the face's period
        per = entity_periods(surf)
        qw = q.copy()
        for a in np.flatnonzero(np.isfinite(per)):
            lo = surf.bounds[a, 0]
            qw[:, a] = lo + np.mod(q[:, a] - lo, per[a])
        ours = geo.inside(np.full(len(q), e), q)
        ref = occ_inside(occ.faces[e], qw)
        bad = np.flatnonzero(ours != ref)
        assert bad.size == 0, f"face {e} ({type(surf).__name__}): {bad.size} of {len(q)} differ, e.g. {q[bad[:3]]}"
        n_in += int(ref.sum())
        # a period away in a closed direction: the same answer
        for a in np.flatnonzero(np.isfinite(per)):
            shift = np.zeros(2)
            shift[a] = per[a] * RNG.choice([-1.0, 1.0])
            np.testing.assert_array_equal(geo.inside(np.full(len(q), e), q + shift), ref)
        checked += len(q)
    assert checked > 3000 and 0.2 * checked < n_in < 0.8 * checked


def test_points_on_the_boundary_are_on_both_faces(part):
    """Points of every loop segment (on a shared edge) are on the face within its band."""
    geo, _ = part
    for e, face in enumerate(geo.model.faces):
        for lp in face.loops:
            P = lp.points
            mids = 0.5 * (P + np.roll(P, -1, axis=0))
            assert geo.inside(np.full(len(P), e), P).all()
            assert geo.inside(np.full(len(P), e), mids).all()


def test_first_samples_of_all_uses_are_linspace_per_use():
    """The first p-curve samples of many edge uses, built at once (``topology._Samples.flat``),
    are each use's own ``np.linspace`` over its range (a line: exactly its two ends), to the
    last bit, in traversal order (backwards for reversed uses); B-spline uses keep theirs."""
    from nagata_snap.cad.topology import _Samples

    n = 40
    t0 = RNG.uniform(-7.0, 7.0, n)
    t1 = t0 + RNG.uniform(1e-3, 7.0, n)
    t0[3], t1[3] = -0.0, 2.5  # a signed zero at the start of a line
    steps = RNG.integers(1, 70, n)
    steps[3] = 1
    rev = RNG.random(n) < 0.5
    spline = {5: np.array([0.0, 0.25, 1.0]), 17: np.array([1.0, 2.0, 3.0, 4.0])}
    t, use = _Samples(np.c_[t0, t1], steps.copy(), np.array(list(spline)), np.array([len(v) for v in spline.values()]),
                      np.concatenate(list(spline.values()))).flat(rev)
    for j in range(n):
        want = spline.get(j, np.array([t0[j], t1[j]]) if steps[j] == 1 else np.linspace(t0[j], t1[j], steps[j] + 1))
        got = t[use == j]
        assert got.tobytes() == (want[::-1] if rev[j] else want).tobytes(), j
    assert np.all(np.diff(use) >= 0)


def _random_spline(rng, closed: bool, clamped: bool = True) -> dict:
    """A B-spline p-curve description: degree 1-4, repeated interior knots, 2D poles, weights
    or None; ``closed``: its first and last poles coincide (its ends, if ``clamped``: knots of
    multiplicity ``p + 1`` at both ends, else ``p`` knots beyond each end of the domain)."""
    p = int(rng.integers(1, 5))
    inner = np.sort(rng.uniform(-2.0, 3.0, int(rng.integers(0, 7))))
    if inner.size and p > 1:
        inner = np.sort(np.r_[inner, inner[:1]])  # a double knot
    a, b = -2.5 + rng.uniform(0, 0.1), 3.5
    ends = ([a] * (p + 1), [b] * (p + 1)) if clamped else (a - np.arange(p, -1, -1) * 0.3, b + np.arange(p + 1) * 0.3)
    knots = np.r_[ends[0], inner, ends[1]]
    n = len(knots) - p - 1
    poles = rng.normal(size=(n, 2))
    if closed:
        poles[-1] = poles[0]
    w = None if rng.random() < 0.4 else rng.uniform(0.3, 2.0, n)
    return {"type": "bspline", "degree": p, "knots": knots, "poles": poles, "weights": w, "range": (a, b)}


def test_packed_splines_evaluate_as_nurbs_curves():
    """``topology._Splines`` (all B-spline p-curves evaluated together) gives, to the last bit,
    what each curve's own :meth:`NurbsCurve.evaluate` gives on the same points: at knots,
    domain ends, inside, and beyond the domain (wrapped on closed curves, clamped on open
    ones); a curve with a single point among many; mixed degrees; unclamped knots."""
    from nagata_snap.cad.topology import _FaceError, _Splines, nurbs_curve

    rng = np.random.default_rng(11)
    descs = [_random_spline(rng, closed=bool(i % 3 == 0), clamped=i % 4 != 2) for i in range(25)]
    splines = _Splines(descs, np.arange(len(descs)))
    ts, cs = [], []
    for c, d in enumerate(descs):
        a, b = d["range"]
        k = int(rng.integers(1, 30)) if c % 5 else 1  # every fifth curve: one point
        t = rng.uniform(a, b, k)
        if k > 1:
            t[:4] = [a, b, d["knots"][d["degree"] + 1], a - 1e-12 * (c % 2) - 0.3 * (c % 4 == 1)][:k]
            t[-1] = b + 1e-12 + 0.2 * (c % 2)
        ts.append(t)
        cs.append(np.full(k, c))
    got = splines(np.concatenate(ts), np.concatenate(cs))
    start = 0
    for c, (d, t) in enumerate(zip(descs, ts, strict=True)):
        want = nurbs_curve(d).evaluate(t)[0][:, :2]
        assert got[start:start + len(t)].tobytes() == want.tobytes(), c
        start += len(t)
    bad = dict(descs[7], knots=descs[7]["knots"][::-1])
    with pytest.raises(_FaceError, match="non-decreasing") as info:
        _Splines([*descs[:7], bad], np.arange(8) + 100)
    assert info.value.face == 107


def test_offset_lengths_are_numpys_norms():
    """``topology._lengths`` (the refinement's metric, coordinate by coordinate) is, to the last
    bit, ``np.linalg.norm`` of the same offsets, on planes' axes and on evaluated tangents."""
    from nagata_snap.cad.projection import evaluate_params, normalize_params
    from nagata_snap.cad.surfaces import analytic_surface
    from nagata_snap.cad.topology import _lengths, _Metric, _tangents

    rng = np.random.default_rng(13)
    for k in (1, 2, 7, 1000):
        a, b = rng.normal(size=k) * 10.0 ** rng.integers(-6, 4, k), rng.normal(size=k)
        U, V = rng.normal(size=(3, k)), rng.normal(size=(3, k)) * 1e3
        want = np.linalg.norm(a[:, None] * U.T + b[:, None] * V.T, axis=1)
        assert _lengths(a, b, U, V).tobytes() == want.tobytes()
    cyl = analytic_surface({"type": "cylinder", "origin": [1.0, 2.0, 3.0], "x": [1.0, 0.0, 0.0], "y": [0.0, 0.8, -0.6],
                            "z": [0.0, 0.6, 0.8], "radius": 2.5}, np.array([[0.0, 6.0], [-1.0, 1.0]]))
    mid = rng.uniform(-1.0, 1.0, (50, 2))
    off = rng.normal(size=(50, 2)) * 1e-3
    Su, Sv = _tangents(cyl, mid)
    _, T = evaluate_params(cyl, normalize_params(cyl, mid), 1)
    assert Su.T.tobytes() == T[:, 0].tobytes() and Sv.T.tobytes() == T[:, 1].tobytes()
    got = _Metric([cyl])(off, mid, np.zeros(50, dtype=np.int64))
    want = np.linalg.norm(off[:, :1] * T[:, 0] + off[:, 1:] * T[:, 1], axis=1)
    assert got.tobytes() == want.tobytes()
    plane = analytic_surface({"type": "plane", "origin": [0.0, 1.0, 2.0], "x": [0.6, 0.8, 0.0], "y": [-0.8, 0.6, 0.0],
                              "z": [0.0, 0.0, 1.0]}, np.array([[-5.0, 5.0], [-5.0, 5.0]]))
    face = np.repeat([0, 1], [20, 30])  # planes and a curved face in one call, then planes only
    got = _Metric([plane, cyl])(off, mid, face)
    on_plane = np.linalg.norm(off[:20, :1] * plane.X + off[:20, 1:] * plane.Y, axis=1)
    _, T = evaluate_params(cyl, normalize_params(cyl, mid[20:]), 1)
    curved = np.linalg.norm(off[20:, :1] * T[:, 0] + off[20:, 1:] * T[:, 1], axis=1)
    assert got.tobytes() == np.r_[on_plane, curved].tobytes()
    assert _Metric([plane])(off[:20], mid[:20], face[:20]).tobytes() == on_plane.tobytes()


def test_packed_splines_first_samples_per_knot_span():
    """``_Splines.first_samples``: per curve :data:`SPLINE_SAMPLES` samples in every interval
    between its range's ends and the distinct knots inside it, then its end (the per-curve
    formula, to the last bit)."""
    from nagata_snap.cad.topology import SPLINE_SAMPLES, _Splines

    rng = np.random.default_rng(12)
    descs = [_random_spline(rng, closed=False) for _ in range(12)]
    t0 = np.array([d["knots"][0] for d in descs]) + rng.uniform(0.0, 1.0, 12) * (rng.random(12) < 0.5)
    t1 = np.array([d["knots"][-1] for d in descs]) - rng.uniform(0.0, 1.0, 12) * (rng.random(12) < 0.5)
    t1[3] = descs[3]["knots"][descs[3]["degree"] + 1]  # the range ends at an interior knot
    counts, t = _Splines(descs, np.arange(12)).first_samples(t0, t1)
    s = np.linspace(0.0, 1.0, SPLINE_SAMPLES + 1)[:-1]
    got = np.split(t, np.cumsum(counts)[:-1])
    for d, a, b, g in zip(descs, t0, t1, got, strict=True):
        k = np.unique(d["knots"])
        k = np.unique(np.r_[a, b, k[(k >= a) & (k <= b)]])
        want = np.r_[(k[:-1, None] + np.outer(np.diff(k), s)).ravel(), b]
        assert g.tobytes() == want.tobytes()


def test_planar_profile_loops_are_sampled_when_first_read(tmp_path, monkeypatch):
    """A planar 2D model's loop polygons are not sampled by ``from_data`` nor by its 2D geometry
    (which snaps onto the edge curves); reading one samples all, exactly as a model sampled at
    once; the 2D edge orientation from the wires' uses is the one from the sampled segments;
    an invalid p-curve is named when the polygons are read (and by a 3D geometry of the model)."""
    import copy

    import parts

    from nagata_snap.cad import topology
    from nagata_snap.cad.read import read_shape

    signs = []
    for name in ("profile_2d", "plate_holes_2d"):
        data = read_shape(str(parts.write_part(name, tmp_path, ("step",))["step"]))
        model = topology.CadModel.from_data(data)
        geo = CadGeometry.from_model(model)
        assert geo.param_dim == 1 and model.is_planar_2d()
        loops = [lp for f in model.faces for lp in f.loops]
        assert loops and all("not sampled" in repr(lp) for lp in loops)
        sign = geo._orientation()
        assert all("not sampled" in repr(lp) for lp in loops)
        with monkeypatch.context() as m:
            m.setattr(topology, "_planar_2d", lambda *a, **k: False)
            eager = topology.CadModel.from_data(data)
        assert all("points" in repr(lp) for f in eager.faces for lp in f.loops)
        for lp, want in zip(loops[::-1], [lp for f in eager.faces for lp in f.loops][::-1], strict=True):
            for attr in ("points", "edges", "band", "senses"):
                assert getattr(lp, attr).tobytes() == getattr(want, attr).tobytes(), attr
        want_sign = np.ones(geo.num_entities)  # the outward sign per edge curve, from the segments
        pos = {e: i for i, e in enumerate(geo._curve_edges.tolist())}
        for f in eager.faces:
            up = np.sign(np.cross(f.surface.X, f.surface.Y)[2]) * (-1.0 if f.reversed else 1.0)
            for lp in f.loops:
                for e, s in zip(lp.edges.tolist(), lp.senses.tolist(), strict=True):
                    if e in pos:
                        want_sign[pos[e]] = s * up
        assert np.array_equal(sign, want_sign)
        signs.append(sign)
    assert (np.concatenate(signs) == -1).any() and (np.concatenate(signs) == 1).any()

    bad = copy.deepcopy(read_shape(str(tmp_path / "profile_2d.step")))
    use = next(u for f in bad["faces"] for w in f["wires"] for u in w["uses"] if u["pcurve"]["type"] == "bspline")
    use["pcurve"]["knots"] = use["pcurve"]["knots"][::-1].copy()
    model = topology.CadModel.from_data(bad)
    CadGeometry.from_model(model)
    with pytest.raises(ValueError, match=r"face 0 \(plane surface\): NurbsCurve: knot vector must be non-decreasing"):
        _ = model.faces[0].loops[0].points
    with pytest.raises(ValueError, match=r"face 0 \(plane surface\)"):
        CadGeometry.from_model(topology.CadModel.from_data(bad), dim=3)


def test_invalid_edge_curve_is_named(tmp_path):
    """An edge whose (batched) analytic curve is invalid: the error names that edge."""
    from nagata_snap.cad.read import read_shape
    from nagata_snap.cad.topology import CadModel

    path = str(tmp_path / "box.step")
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        gmsh.model.occ.synchronize()
        gmsh.write(path)
    finally:
        gmsh.finalize()
    data = read_shape(path)
    lines = [i for i, e in enumerate(data["edges"]) if e["curve"] is not None and e["curve"]["type"] == "line"]
    bad = lines[len(lines) // 2]
    data["edges"][bad]["curve"]["direction"] = [0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match=rf"edge {bad} \(line curve\): line direction must be non-zero"):
        CadModel.from_data(data)


def test_band_test_of_all_faces_at_once_is_excess_face_by_face(part):
    """``inside`` (with the band: all faces' queries at once, through the loop table) says
    what the face-by-face ``excess <= 0`` says, on points of every face's box, on its loops,
    within and just beyond their bands, and a period away."""
    geo, _ = part
    trims = geo.trims
    ent, q = [], []
    for e, face in enumerate(geo.model.faces):
        P = np.concatenate([lp.points for lp in face.loops])
        lo, hi = P.min(axis=0), P.max(axis=0)
        span = np.maximum(hi - lo, 1e-9)
        pts = [lo - 0.05 * span + RNG.random((200, 2)) * 1.1 * span, P]
        for scale in (1e-7, 1e-5, 1e-3):  # about the bands' widths, either side of the loops
            pts.append(P + scale * span * RNG.normal(size=P.shape))
        per = entity_periods(face.surface)
        pts.append(pts[0] + np.where(np.isfinite(per), per, 0.0))
        pts = np.concatenate(pts)
        ent.append(np.full(len(pts), e))
        q.append(pts)
    ent, q = np.concatenate(ent), np.concatenate(q)
    ours = trims.inside(ent, q)
    assert np.array_equal(ours, trims.excess(ent, q) <= 0.0)
    assert 0 < ours.sum() < len(ours)
