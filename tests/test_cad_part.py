"""CAD mode on a multi-face trimmed part, checked against OpenCASCADE itself.

``meshes/occ_part.igs`` (written by OCC through gmsh, ``meshes/make_iges.py``):
the unit box minus a cylinder of radius 0.2 on the axis (0.5, 0.5, z): six
planar faces (144 trimmed planes, the top and bottom ones with the hole as an
inner loop) and the hole's wall (a surface of revolution trimmed to the box).
The IGES file is imported into gmsh's OCC kernel, sewn into a solid and meshed
(:func:`generate.iges_solid`, one facet tag per face); ``CadGeometry.from_iges``
reads the same file (NURBS surfaces and trimming loops); ``Snapper`` refines
uniformly and snaps.  Every snapped boundary vertex is then compared with OCC's
own faces: its distance to the nearest face, counted only where OCC classifies
the foot point as inside the trimmed face (``gmsh.model.isInside``), so a vertex
on a surface's extension beyond its face (e.g. the top plane inside the hole)
fails the check.
"""

from __future__ import annotations

import math
import os

import gmsh
import numpy as np
import pytest
from mpi4py import MPI

import dolfinx.mesh
import generate

from nagata_snap import Snapper
from nagata_snap.cad import CadGeometry
from nagata_snap.mesh import bisect
from nagata_snap.smoothing.quality import inverted_cells

SIZE = math.sqrt(3.0)  # model size: the box diagonal
H = 0.2  # coarse mesh size
LEVELS = 2
R_HOLE, C_HOLE = 0.2, (0.5, 0.5)


class OccModel:
    """The part's faces in gmsh/OCC, for distances from OCC's own geometry.

    ``gmsh.model.getClosestPoint`` projects onto a face's *untrimmed* surface,
    and on the surface of revolution it is only ~1e-7 accurate (its Extrema
    stops at the parameter ``pi/2`` for points within ~4e-7 of it); the foot
    point is polished by Newton steps on OCC's own parametrisation (gmsh's
    ``getValue``/``getDerivative``/``getSecondDerivative``), then classified with
    ``gmsh.model.isInside`` (trimmed face).  Points whose foot point is inside no
    face within tolerance are measured to the edges (curves, parameter within
    bounds).
    """

    def __init__(self, path: str):
        gmsh.model.add(os.path.basename(path))
        occ = gmsh.model.occ
        occ.importShapes(path)
        occ.synchronize()
        # sew the faces so that shared edges are one curve (the planes' exact circles)
        occ.healShapes([], tolerance=generate.IGES_HEAL_TOLERANCE, sewFaces=True, makeSolids=False)
        occ.synchronize()
        self.faces = [t for _, t in gmsh.model.getEntities(2)]
        self.curves = [t for _, t in gmsh.model.getEntities(1)]
        self.types = {f: gmsh.model.getType(2, f) for f in self.faces}

    @staticmethod
    def _polish(tag: int, X: np.ndarray, iters: int = 4) -> tuple[np.ndarray, np.ndarray]:
        _, uv = gmsh.model.getClosestPoint(2, tag, X.ravel())
        uv = np.reshape(uv, (-1, 2)).copy()
        for _ in range(iters):  # Newton on |S(u, v) - X|^2
            S = np.reshape(gmsh.model.getValue(2, tag, uv.ravel()), (-1, 3))
            D = np.reshape(gmsh.model.getDerivative(2, tag, uv.ravel()), (-1, 2, 3))
            Hs = np.reshape(gmsh.model.getSecondDerivative(2, tag, uv.ravel()), (-1, 3, 3))
            r = S - X
            g = np.einsum("nij,nj->ni", D, r)
            a = np.einsum("nj,nj->n", D[:, 0], D[:, 0]) + np.einsum("nj,nj->n", Hs[:, 0], r)
            b = np.einsum("nj,nj->n", D[:, 0], D[:, 1]) + np.einsum("nj,nj->n", Hs[:, 1], r)
            c = np.einsum("nj,nj->n", D[:, 1], D[:, 1]) + np.einsum("nj,nj->n", Hs[:, 2], r)
            det = a * c - b * b
            ok = (a > 0) & (det > 1e-14 * np.abs(a * c))
            det = np.where(ok, det, 1.0)
            uv[:, 0] -= np.where(ok, (c * g[:, 0] - b * g[:, 1]) / det, 0.0)
            uv[:, 1] -= np.where(ok, (a * g[:, 1] - b * g[:, 0]) / det, 0.0)
        S = np.reshape(gmsh.model.getValue(2, tag, uv.ravel()), (-1, 3))
        return np.linalg.norm(S - X, axis=1), uv

    def distance(self, X: np.ndarray, tol: float) -> np.ndarray:
        """Distance of each point to the part's (trimmed) faces, exact below ``tol``."""
        X = np.asarray(X, dtype=float)
        best = np.full(len(X), np.inf)
        for f in self.faces:
            d, uv = self._polish(f, X)
            for i in np.flatnonzero(d < best):  # classify only candidates
                if gmsh.model.isInside(2, f, uv[i], parametric=True):
                    best[i] = d[i]
        far = np.flatnonzero(best > tol)
        if far.size:  # on an edge, classified outside both faces: distance to the edges
            for c in self.curves:
                cp, t = gmsh.model.getClosestPoint(1, c, X[far].ravel())
                lo, hi = gmsh.model.getParametrizationBounds(1, c)
                t = np.asarray(t)
                d = np.linalg.norm(np.reshape(cp, (-1, 3)) - X[far], axis=1)
                ok = (t >= lo[0] - 1e-12) & (t <= hi[0] + 1e-12)
                best[far] = np.where(ok & (d < best[far]), d, best[far])
        return best

    def plane(self, f: int) -> tuple[int, float] | None:
        """``(axis, value)`` of an axis-aligned planar face, else None."""
        if self.types[f] != "Plane":
            return None
        lo_hi = np.reshape(gmsh.model.getBoundingBox(2, f), (2, 3))
        axis = int(np.argmin(np.diff(lo_hi, axis=0)))
        return axis, float(round(lo_hi[:, axis].mean(), 6))


@pytest.fixture(scope="module")
def part(tmp_path_factory) -> str:
    """``occ_part.igs`` written by gmsh/OCC (``meshes/make_iges.py``) into a temporary folder."""
    import make_iges

    paths = make_iges.write_occ_models(tmp_path_factory.mktemp("occ"))
    return str(next(p for p in paths if p.name == "occ_part.igs"))


@pytest.fixture(scope="module")
def occ(part):
    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("reference")
        yield OccModel(part)
    finally:
        gmsh.finalize()


def boundary_data(mesh, ft):
    """``(facet node indices (nf, 3), facet tag (nf,))`` of the tagged boundary facets."""
    nodes = dolfinx.mesh.entities_to_geometry(mesh, 2, ft.indices)
    return nodes, np.asarray(ft.values)


def test_reference_checker_sees_face_extensions(occ):
    """The OCC distance counts trimmed faces only: the top plane's extension inside
    the hole is 0.2 away from the part, the rim and a face point are on it."""
    X = np.array([[0.5, 0.5, 1.0], [0.45, 0.5, 1.0], [0.7, 0.5, 1.0], [0.3, 0.2, 1.0], [0.5, 0.3, 0.4]])
    d = occ.distance(X, 1e-9)
    np.testing.assert_allclose(d[2:], 0.0, rtol=0, atol=1e-15)
    # off the faces: measured to OCC's sewn edge curves (B-splines ~1e-5 from the circle)
    np.testing.assert_allclose(d[:2], [0.2, 0.15], rtol=0, atol=1e-5)


def test_occ_part_snapping_matches_occ(occ, part):
    md = generate.iges_solid(MPI.COMM_WORLD, part, h=H)
    mesh, ft = md.mesh, md.facet_tags
    geo = CadGeometry.from_iges(part)  # OpenCASCADE reads and sews the faces
    assert geo.num_entities == 7 and geo.trims is not None and geo.topology is not None
    assert sorted(np.unique(ft.values).tolist()) == sorted(occ.faces)

    # attach: every CAD face's facets go to one NURBS surface, a different one per face
    nodes, tags = boundary_data(mesh, ft)
    root = geo.attach(mesh.geometry.x[nodes]).root
    pairs = np.unique(np.c_[tags, root], axis=0)
    assert len(pairs) == len(occ.faces) == len(np.unique(pairs[:, 1]))

    snapper = Snapper(mesh, ft, geo)
    tol = 1e-9 * SIZE
    for level in range(1, LEVELS + 1):
        prev = mesh
        mesh, ft, *_, report = snapper.refine(mesh)
        g = report.geometry
        assert g.n_unresolved == 0
        # the rim vertices between two rim vertices go onto the rim circle (CAD
        # edge), not onto the top plane inside the hole; they are on both faces
        assert g.n_edge_vertices > 0
        assert g.max_edge_gap <= 1e-13 * SIZE
        assert len(g.iterations_histogram) - 1 <= 7

        nodes, tags = boundary_data(mesh, ft)
        x = mesh.geometry.x
        vb = np.unique(nodes)
        d = occ.distance(x[vb], tol)
        assert d.max() <= tol, f"level {level}: vertex {x[vb][np.argmax(d)]} is {d.max():.3e} from the OCC part"

        # flat faces stay flat; the hole's wall stays a cylinder within the box
        for f in occ.faces:
            v = np.unique(nodes[tags == f])
            pl = occ.plane(f)
            if pl is not None:
                axis, value = pl
                assert np.abs(x[v, axis] - value).max() <= 1e-13
            else:
                r = np.hypot(x[v, 0] - C_HOLE[0], x[v, 1] - C_HOLE[1])
                assert np.abs(r - R_HOLE).max() <= 1e-13
                assert x[v, 2].min() >= -1e-14 and x[v, 2].max() <= 1 + 1e-14

        # no inverted cells relative to the straight refinement of the previous level
        prev.topology.create_entities(1)
        straight, *_ = bisect.refine(prev, None)  # the snapper's refinement, not snapped
        cells = mesh.geometry.dofmaps[0]
        np.testing.assert_array_equal(straight.geometry.dofmaps[0], cells)
        assert inverted_cells(x, straight.geometry.x, cells, 3).size == 0
        assert report.inverted_after_smoothing == 0


# ----------------------------------------------------------------------
# partial sphere, cone, cylinder and torus faces (make_iges.build_occ_features)
# ----------------------------------------------------------------------
def on_features(X: np.ndarray) -> np.ndarray:
    """Distance of points to the features part's faces, each restricted to its trim.

    Exact implicit distances of the planes, the sphere, the cylinder and the
    torus (the cone's is its exact distance near the surface); each face
    counts only within its region, so a point on a surface's extension beyond
    its face is not on the part.
    """
    import make_iges

    f = make_iges.OCC_FEATURES
    x, y, z = X.T
    e = 1e-9
    cx, cy, cz, Rd = f["dome"]
    hx, hy, _, _, _, _, rh = f["hole"]
    _, _, z0, _, _, hz, _, rtop = f["sink"]
    tx, ty, _, Rt, rt = f["groove"]
    zt = 0.5
    r_sink = rtop * (zt - z0) / hz  # countersink radius on the top face
    z_sink = z0 + hz * rh / rtop  # where the countersink meets the hole
    r_dome = math.sqrt(Rd**2 - (zt - cz) ** 2)  # dome circle on the top face
    rs = np.hypot(x - hx, y - hy)
    rd = np.hypot(x - tx, y - ty)
    side = (z > -e) & (z < zt + e)
    faces = [
        (np.abs(x), side), (np.abs(x - 1), side), (np.abs(y), side), (np.abs(y - 1), side),
        (np.abs(z - zt), (rs >= r_sink - e) & (rd >= r_dome - e)),
        (np.abs(z), (rs >= rh - e) & ((rd >= Rt + rt - e) | (rd <= Rt - rt + e))),
        (np.abs(np.linalg.norm(X - [cx, cy, cz], axis=1) - Rd), z >= zt - e),
        (np.abs(rs - rtop * (z - z0) / hz) * hz / math.hypot(hz, rtop), (z >= z_sink - e) & (z <= zt + e)),
        (np.abs(rs - rh), (z >= -e) & (z <= z_sink + e)),
        (np.abs(np.hypot(rd - Rt, z) - rt), z >= -e),
    ]
    d = np.full(len(X), np.inf)
    for res, region in faces:
        d = np.where(region & (res < d), res, d)
    return d


def test_occ_features_place_on_trimmed_curved_faces(tmp_path):
    """Partial sphere (dome), cone (countersink), cylinder (hole) and torus (groove)
    faces, trimmed by circles shared with planes and with each other.  Refinement
    is emulated (``split_triangles``: straight midpoints, parametric-midpoint
    seeds) to test ``CadGeometry.place`` itself, without the smoothing: at this
    coarse size (h = 0.1 against a groove of radius 0.06) ``Snapper``'s repair
    moves some vertices only part of the way, and its smoothing of a finer
    mesh takes minutes."""
    import make_iges
    from test_cad_geometry import split_triangles

    path = make_iges.write_occ_features(tmp_path)
    geo = CadGeometry.from_iges(path)
    assert geo.num_entities == 11 and geo.trims is not None
    md = generate.occ_features(MPI.COMM_WORLD, h=0.1)
    nodes, tags = boundary_data(md.mesh, md.facet_tags)
    x = md.mesh.geometry.x[nodes]
    assert on_features(x.reshape(-1, 3)).max() <= 1e-14
    rec = geo.attach(x)
    pairs = np.unique(np.c_[tags, rec.root], axis=0)
    assert len(pairs) == 11 == len(np.unique(pairs[:, 1])) == len(np.unique(tags))
    planar = [e for e in range(11) if getattr(geo.entities[e], "kind", "") == "plane"]
    assert len(planar) == 7
    for level in range(2):
        st, rec = split_triangles(x, rec)
        pts, rec, report = geo.place(rec, st)
        assert report.n_unresolved == 0
        assert report.n_edge_vertices > 0 and report.max_edge_gap <= 1e-13
        d = on_features(pts.reshape(-1, 3))
        assert d.max() <= 1e-9 * SIZE, f"level {level + 1}: {pts.reshape(-1, 3)[np.argmax(d)]} is {d.max():.3e} off"
        for e in planar:  # flat faces stay flat
            v = pts[rec.root == e] @ geo.entities[e].Z
            assert np.ptp(v) <= 1e-13
        x = pts
