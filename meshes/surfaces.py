"""Triangulated surfaces with exact geometry, for Nagata accuracy tests and benchmarks.

Each function returns ``(points (nv, 3), triangles (F, 3), exact)`` where
``exact`` has ``normal(x)`` and ``distance(x)`` (unsigned distance to the exact
surface).  Triangles are wound with outward normals.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np


def _dedupe(points: np.ndarray, tris: np.ndarray, tol: float = 1e-12):
    key = np.round(points / tol).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return points[first], inv.reshape(-1)[tris]


def _subdivide(points: np.ndarray, tris: np.ndarray, project) -> tuple[np.ndarray, np.ndarray]:
    a, b, c = tris.T
    p = points
    mab, mbc, mca = (p[a] + p[b]) / 2, (p[b] + p[c]) / 2, (p[c] + p[a]) / 2
    n, F = len(p), len(tris)
    pts = np.concatenate([p, mab, mbc, mca])
    iab, ibc, ica = n + np.arange(F), n + F + np.arange(F), n + 2 * F + np.arange(F)
    new = np.concatenate(
        [np.c_[a, iab, ica], np.c_[iab, b, ibc], np.c_[ica, ibc, c], np.c_[iab, ibc, ica]]
    )
    pts, new = _dedupe(pts, new)
    return project(pts), new


def sphere_octahedron(level: int = 1, radius: float = 1.0):
    """Octahedron inscribed in a sphere, each face split into ``4**level`` triangles.

    ``level = 1`` is Neto's (2010) sphere mesh 1: 32 triangles, 18 nodes,
    longest edge 1.00 (seed 000, Table 2).
    """
    p = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    t = np.array(
        [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
    )

    def project(x):
        return radius * x / np.linalg.norm(x, axis=1, keepdims=True)

    p = project(p)
    for _ in range(level):
        p, t = _subdivide(p, t, project)
    exact = SimpleNamespace(
        normal=lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True),
        distance=lambda x: np.abs(np.linalg.norm(x, axis=-1) - radius),
    )
    return p, t, exact


def _radial_normal(x):
    """Unit normal of a cylinder of axis z: the radial direction."""
    r = np.hypot(x[..., 0], x[..., 1])
    return np.stack([x[..., 0] / r, x[..., 1] / r, 0 * r], axis=-1)


def _cylinder_distance(radius: float, height: float):
    """Unsigned distance from the closed cylinder (axis z, centred at the origin)."""

    def distance(x):
        r = np.hypot(x[..., 0], x[..., 1])
        q0, q1 = r - radius, np.abs(x[..., 2]) - height / 2
        outside = np.hypot(np.maximum(q0, 0), np.maximum(q1, 0))
        inside = np.minimum(np.maximum(q0, q1), 0)
        return np.abs(outside + inside)

    return distance


def closed_cylinder(n_around: int, radius: float = 1.0, height: float = 1.0):
    """Closed right cylinder (side and both discs), axis z, centred at the origin.

    The side has ``n_around`` segments and ``ceil(n_around * height / (2 pi R))``
    rows of quads split in two; each disc is a fan of ``n_around`` triangles
    around its centre.  Returns tags too: ``(points, tris, exact, tags)`` with
    tag 1 on the side and 2 on the discs.
    """
    n = n_around
    rows = max(1, int(np.ceil(n * height / (2 * np.pi * radius))))
    th = 2 * np.pi * np.arange(n) / n
    z = np.linspace(-height / 2, height / 2, rows + 1)
    ring = np.c_[radius * np.cos(th), radius * np.sin(th)]
    side = np.concatenate([np.c_[ring, np.full(n, zz)] for zz in z])
    idx = np.arange(n)
    tris = []
    for r in range(rows):
        a = r * n + idx
        b = r * n + (idx + 1) % n
        c = (r + 1) * n + (idx + 1) % n
        d = (r + 1) * n + idx
        tris += [np.c_[a, b, c], np.c_[a, c, d]]
    nside = len(side)
    centres = np.array([[0, 0, -height / 2], [0, 0, height / 2]])
    pts = np.concatenate([side, centres])
    bottom = np.c_[np.full(n, nside), (idx + 1) % n, idx]
    top = np.c_[np.full(n, nside + 1), rows * n + idx, rows * n + (idx + 1) % n]
    tris = np.concatenate([*tris, bottom, top])
    tags = np.r_[np.ones(2 * rows * n, int), np.full(2 * n, 2)]

    distance = _cylinder_distance(radius, height)

    return pts, tris, SimpleNamespace(normal=_radial_normal, distance=distance), tags


def circle_polygon(n: int, radius: float = 1.0, centre=(0.0, 0.0), jitter: float = 0.0, seed: int = 0):
    """Counter-clockwise ``n``-gon inscribed in a circle (optionally with angular jitter)."""
    th = 2 * np.pi * np.arange(n) / n
    if jitter:
        th = th + jitter * (2 * np.pi / n) * np.random.default_rng(seed).uniform(-0.5, 0.5, n)
    pts = np.c_[centre[0] + radius * np.cos(th), centre[1] + radius * np.sin(th)]
    segs = np.c_[np.arange(n), (np.arange(n) + 1) % n]
    c = np.asarray(centre, float)
    exact = SimpleNamespace(
        normal=lambda x: (x[..., :2] - c) / np.linalg.norm(x[..., :2] - c, axis=-1, keepdims=True),
        distance=lambda x: np.abs(np.linalg.norm(x[..., :2] - c, axis=-1) - radius),
    )
    return pts, segs, exact


def barycentric_grid(nfv: int, m: int) -> np.ndarray:
    """``(k, nfv)`` barycentric sample points: ``m + 1`` per edge."""
    if nfv == 2:
        t = np.linspace(0, 1, m + 1)
        return np.c_[1 - t, t]
    i, j = np.meshgrid(np.arange(m + 1), np.arange(m + 1), indexing="ij")
    keep = i + j <= m
    l2, l3 = i[keep] / m, j[keep] / m
    return np.c_[1 - l2 - l3, l2, l3]


def nagata_surface_error(geo, dist, tag: int | None = None, per_edge: int | None = None) -> float:
    """Max ``dist`` of densely sampled Nagata patches of ``geo`` from an exact surface.

    Args:
        geo: a ``nagata_snap.NagataGeometry``.
        dist: ``f(x (..., 3)) -> (...)`` distance from the exact curve / surface.
        tag: only the patches of this facet tag (default: every snapped patch).
        per_edge: sample intervals per edge (default 200 in 2D, 30 in 3D: 496
            samples per triangle).
    """
    sel = np.flatnonzero(geo.snap if tag is None else geo.tag == tag)
    nfv = geo.ids.shape[1]
    g = barycentric_grid(nfv, per_edge or (200 if nfv == 2 else 30))
    err = 0.0
    for lo in range(0, len(sel), 2000):  # bounded memory on fine meshes
        s = sel[lo:lo + 2000]
        err = max(err, float(dist(geo.evaluate(s, np.broadcast_to(g, (len(s), *g.shape)))).max()))
    return err


# --------------------------------------------------------------------------
# gmsh (OpenCASCADE) surface meshes of smooth and creased solids, exact geometry
# --------------------------------------------------------------------------
def torus_exact(R: float = 1.0, r: float = 0.4) -> SimpleNamespace:
    """Normal and distance of the torus with axis z, major radius ``R``, minor ``r``."""

    def normal(x):
        rho = np.hypot(x[..., 0], x[..., 1])
        d = x - np.stack([R * x[..., 0] / rho, R * x[..., 1] / rho, 0 * rho], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def distance(x):
        return np.abs(np.hypot(np.hypot(x[..., 0], x[..., 1]) - R, x[..., 2]) - r)

    return SimpleNamespace(normal=normal, distance=distance)


def ellipsoid_exact(axes=(1.0, 0.7, 0.5)) -> SimpleNamespace:
    """Normal and distance of the ellipsoid with semi-axes ``axes`` along x, y, z.

    The closest point is ``a_i^2 x_i / (a_i^2 + t)`` with ``t`` the root of
    ``sum (a_i x_i / (a_i^2 + t))^2 = 1`` nearest 0 (Newton from 0; valid for
    points within a fraction of the smallest radius of curvature).
    """
    a2 = np.asarray(axes, dtype=float) ** 2

    def normal(x):
        g = x / a2
        return g / np.linalg.norm(g, axis=-1, keepdims=True)

    def distance(x):
        t = np.zeros(x.shape[:-1])
        for _ in range(30):
            q = x / (a2 + t[..., None])
            step = (np.sum(a2 * q**2, axis=-1) - 1) / (2 * np.sum(a2 * q**2 / (a2 + t[..., None]), axis=-1))
            t = t + step
            if np.abs(step).max() < 1e-15:
                break
        return np.linalg.norm(x - a2 * x / (a2 + t[..., None]), axis=-1)

    return SimpleNamespace(normal=normal, distance=distance)


def _orient_entities(points: np.ndarray, tris: np.ndarray, entity: np.ndarray) -> np.ndarray:
    """Flip whole gmsh surfaces so the closed surface is consistently wound and outward.

    gmsh winds each surface's triangles by that surface's parametrisation;
    the combination of per-surface flips that traverses every edge once in
    each direction and encloses a positive volume is returned.
    """
    ents = np.unique(entity)
    for signs in range(2 ** len(ents)):
        flip = np.isin(entity, ents[[(signs >> k) & 1 == 1 for k in range(len(ents))]])
        t = np.where(flip[:, None], tris[:, [0, 2, 1]], tris)
        directed = t[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        if len(np.unique(directed, axis=0)) != len(directed):
            continue
        x = points[t]
        if np.einsum("fi,fi->f", x[:, 0], np.cross(x[:, 1], x[:, 2])).sum() > 0:
            return t
    raise ValueError("the gmsh surfaces do not close into a consistently orientable surface")


def gmsh_occ_surface(build, h: float, algorithm: int = 6):
    """Surface triangles of the OpenCASCADE solid ``build()`` makes, gmsh sizes ``MeshSizeMin = MeshSizeMax = h``.

    ``build`` runs in a fresh gmsh model and creates one solid with
    ``gmsh.model.occ``.  These are the boundary triangles gmsh's volume mesh
    of the solid would have (gmsh meshes the surfaces first and keeps them).
    ``algorithm`` is gmsh's ``Mesh.Algorithm`` (6 Frontal-Delaunay, the
    default; 5 Delaunay, 1 MeshAdapt give other meshes of the same size).

    Returns:
        ``(points (nv, 3), triangles (F, 3) outward, tags (F,))``, ``tags``
        the gmsh surface (CAD face) of each triangle.
    """
    import gmsh

    import generate

    from nagata_snap.meshing import gmsh_session

    sizes = {"Mesh.MeshSizeMax": h, "Mesh.MeshSizeMin": h, "Mesh.Algorithm": algorithm}
    with gmsh_session("surface", {**generate._fixed_options(False), **sizes}):  # restored afterwards
        build()
        gmsh.model.occ.synchronize()
        gmsh.model.mesh.generate(2)
        node_tags, xyz, _ = gmsh.model.mesh.getNodes()
        tris, ent = [], []
        for _, s in gmsh.model.getEntities(2):
            t = gmsh.model.mesh.getElements(2, s)[2][0].reshape(-1, 3)
            tris.append(t)
            ent.append(np.full(len(t), s))
    order = np.argsort(node_tags)
    tris = order[np.searchsorted(node_tags[order], np.concatenate(tris))]
    used, inv = np.unique(tris, return_inverse=True)
    points, tris, ent = xyz.reshape(-1, 3)[used], inv.reshape(-1, 3), np.concatenate(ent)
    return points, _orient_entities(points, tris, ent), ent


def gmsh_surface(kind: str, h: float, algorithm: int = 6):
    """Surface mesh of a solid meshed by gmsh with ``MeshSizeMin = MeshSizeMax = h``.

    ``kind``: ``"torus"`` (R = 1, r = 0.4, axis z), ``"ellipsoid"``
    (semi-axes 1, 0.7, 0.5) or ``"cylinder"`` (closed, R = 1, height 1,
    axis z, centred at the origin: sharp rims).

    Returns:
        ``(points (nv, 3), triangles (F, 3) outward, exact, tags (F,))`` with
        ``tags`` the gmsh surface of each triangle (cylinder: 1 side, 2 and 3
        the discs) and ``exact`` as for the analytic surfaces here (cylinder:
        the side's normal).  ``algorithm``: as for :func:`gmsh_occ_surface`.
    """
    import gmsh

    def build():
        occ = gmsh.model.occ
        if kind == "torus":
            occ.addTorus(0, 0, 0, 1.0, 0.4)
        elif kind == "ellipsoid":
            occ.dilate([(3, occ.addSphere(0, 0, 0, 1.0))], 0, 0, 0, 1.0, 0.7, 0.5)
        else:
            occ.addCylinder(0, 0, -0.5, 0, 0, 1.0, 1.0)

    if kind not in ("torus", "ellipsoid", "cylinder"):
        raise ValueError(f"unknown surface {kind!r}")
    points, tris, ent = gmsh_occ_surface(build, h, algorithm)
    if kind == "torus":
        exact = torus_exact()
    elif kind == "ellipsoid":
        exact = ellipsoid_exact()
    else:
        exact = SimpleNamespace(normal=_radial_normal, distance=_cylinder_distance(1.0, 1.0))
    return points, tris, exact, ent


def roof_prism(ridge_deg: float = 30.0):
    """Builder (for :func:`gmsh_occ_surface`) of a prism whose roof ridge turns by ``ridge_deg``.

    Cross-section in the xz plane: the rectangle [-1, 1] x [0, 1] with a gable
    roof of slopes ``ridge_deg / 2`` up to the ridge line x = 0; extruded 1.5
    along y.  The ridge is the line x = 0, z = 1 + tan(ridge_deg / 2).
    """
    import gmsh

    def build():
        occ = gmsh.model.occ
        top = 1.0 + np.tan(np.radians(ridge_deg / 2))
        pts = [occ.addPoint(*q) for q in [(-1, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, top), (-1, 0, 1)]]
        loop = occ.addCurveLoop([occ.addLine(pts[i], pts[(i + 1) % 5]) for i in range(5)])
        occ.extrude([(2, occ.addPlaneSurface([loop]))], 0, 1.5, 0)

    return build


def half_torus():
    """Builder of the torus R = 1, r = 0.4 (axis z) cut by the plane z = 0: sharp 90-degree rims.

    The flat face is the annulus 0.6 <= rho <= 1.4 in z = 0; the curved face
    is the lower half of the torus (:func:`torus_exact`).
    """
    import gmsh

    def build():
        occ = gmsh.model.occ
        occ.intersect([(3, occ.addTorus(0, 0, 0, 1.0, 0.4))], [(3, occ.addBox(-2, -2, -1, 4, 4, 1))])

    return build


def filleted_box(radius: float = 0.3):
    """Builder of the box [0, 1]^3 with its edge x = y = 1 rounded by a fillet of ``radius``.

    The fillet is a quarter cylinder of axis ``(1 - radius, 1 - radius, z)``
    meeting the faces x = 1 and y = 1 tangentially along the lines
    ``(1, 1 - radius, z)`` and ``(1 - radius, 1, z)``.
    """
    import gmsh

    def build():
        occ = gmsh.model.occ
        box = occ.addBox(0, 0, 0, 1, 1, 1)
        occ.synchronize()
        edge = [e for _, e in gmsh.model.getBoundary([(3, box)], combined=False, oriented=False,
                                                     recursive=True)
                if np.allclose(gmsh.model.occ.getCenterOfMass(1, e), (1, 1, 0.5))]
        occ.fillet([box], edge, [radius])

    return build


def ellipse_polygon(n: int, a: float = 1.0, b: float = 0.5, jitter: float = 0.3, seed: int = 0):
    """Counter-clockwise ``n``-gon inscribed in the ellipse ``(x/a)^2 + (y/b)^2 = 1``.

    Vertices at nearly equal arc length (perturbed by ``jitter`` of a segment).

    Returns:
        ``(points (n, 2), segments (n, 2), exact)`` with exact normal and distance.
    """
    t = np.linspace(0, 2 * np.pi, 20001)
    arc = np.r_[0, np.cumsum(np.hypot(np.diff(a * np.cos(t)), np.diff(b * np.sin(t))))]
    target = (np.arange(n) + jitter * np.random.default_rng(seed).uniform(-0.5, 0.5, n)) * arc[-1] / n
    th = np.interp(target % arc[-1], arc, t)
    a2 = np.array([a * a, b * b])

    def normal(x):
        g = x[..., :2] / a2
        return g / np.linalg.norm(g, axis=-1, keepdims=True)

    def distance(x):
        x = x[..., :2]
        s = np.zeros(x.shape[:-1])
        for _ in range(40):
            q = x / (a2 + s[..., None])
            s = s + (np.sum(a2 * q**2, axis=-1) - 1) / (2 * np.sum(a2 * q**2 / (a2 + s[..., None]), axis=-1))
        return np.linalg.norm(x - a2 * x / (a2 + s[..., None]), axis=-1)

    segs = np.c_[np.arange(n), (np.arange(n) + 1) % n]
    return np.c_[a * np.cos(th), b * np.sin(th)], segs, SimpleNamespace(normal=normal, distance=distance)
