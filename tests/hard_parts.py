"""Coarse gmsh/OCC meshes of machined-part features that make snapping hard.

Test and benchmark helper (a stand-in until ``meshes/parts.py`` provides
the parts): each builder makes the solid with gmsh's OpenCASCADE kernel,
meshes it coarsely with curvature sizing (12 elements per 2 pi, largest
size 0.1 of the bounding-box diagonal, as a user would) and returns
``MeshData`` with one facet tag per CAD face (its gmsh face tag).

* ``plate``: a plate with two through-holes, a counterbore, filleted
  vertical edges and a pocket;
* ``thin_wall``: a quarter of a cylindrical shell, thinner than the mesh size;
* ``concave_cylinder``: a block with a cylindrical groove (concave face);
* ``reentrant_fillet``: an L-shaped block whose re-entrant edge is filleted.

:func:`part` meshes one; :func:`write_iges` writes it as IGES (gmsh/OCC) and
:func:`from_iges` meshes the solid read back from that file, for CAD mode.
"""

from __future__ import annotations

import math

import gmsh
import numpy as np

import generate

#: Curvature sizing (elements per 2 pi) and largest size (fraction of the diagonal).
CURVATURE_ELEMENTS = 12
SIZE_OF_DIAGONAL = 0.1


def _mesh(vols: list[int]) -> None:
    lo = np.array(gmsh.model.getBoundingBox(-1, -1)[:3])
    hi = np.array(gmsh.model.getBoundingBox(-1, -1)[3:])
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", CURVATURE_ELEMENTS)
    gmsh.option.setNumber("Mesh.MeshSizeMax", SIZE_OF_DIAGONAL * float(np.linalg.norm(hi - lo)))
    faces = generate._boundary_surfaces([(3, v) for v in vols])
    gmsh.model.addPhysicalGroup(3, vols, generate.VOLUME)
    for t in faces:  # one physical group per CAD face
        gmsh.model.addPhysicalGroup(2, [t], t)
    gmsh.model.mesh.generate(3)


def _vertical_edges(height: float) -> list[int]:
    out = []
    for _, e in gmsh.model.getEntities(1):
        b = gmsh.model.getBoundingBox(1, e)
        if abs(b[5] - b[2]) > 0.5 * height:
            out.append(e)
    return out


def _build(comm, name, make):
    def build():
        make()
        gmsh.model.occ.synchronize()
        _mesh([t for _, t in gmsh.model.getEntities(3)])

    return generate._build_and_convert(comm, name, build, 3, msh_file=None, verbose=False, root=0)


def _plate():
    """4 x 2 x 0.6 plate: holes r = 0.3 (with a counterbore r = 0.5, depth 0.2) and r = 0.25,
    vertical edges filleted (r = 0.4), a 0.6 x 1.2 pocket of depth 0.3."""
    occ = gmsh.model.occ
    box = occ.addBox(0, 0, 0, 4.0, 2.0, 0.6)
    occ.synchronize()
    vol = occ.fillet([box], _vertical_edges(0.6), [0.4])[0][1]
    tools = [occ.addCylinder(1.0, 1.0, -0.1, 0, 0, 0.8, 0.3),
             occ.addCylinder(1.0, 1.0, 0.4, 0, 0, 0.3, 0.5),
             occ.addCylinder(3.0, 1.0, -0.1, 0, 0, 0.8, 0.25),
             occ.addBox(2.0, 0.4, 0.3, 0.6, 1.2, 0.5)]
    occ.cut([(3, vol)], [(3, t) for t in tools])


def _thin_wall():
    """Quarter of a cylindrical shell: radii 1 and 0.96, height 0.5 (wall 0.04, mesh size ~0.15)."""
    occ = gmsh.model.occ
    outer = occ.addCylinder(0, 0, 0, 0, 0, 0.5, 1.0, angle=math.pi / 2)
    inner = occ.addCylinder(0, 0, -0.1, 0, 0, 0.7, 0.96, angle=math.pi / 2)
    occ.cut([(3, outer)], [(3, inner)])


def _concave_cylinder():
    """2 x 1 x 1 block with a groove: a cylinder r = 0.6 along x, axis on the top face."""
    occ = gmsh.model.occ
    box = occ.addBox(0, 0, 0, 2.0, 1.0, 1.0)
    cyl = occ.addCylinder(-0.1, 0.5, 1.0, 2.2, 0, 0, 0.6)
    occ.cut([(3, box)], [(3, cyl)])


def _reentrant_fillet():
    """L-shaped block (2 x 2 minus the 1 x 1 quadrant, height 0.5), re-entrant edge filleted r = 0.2."""
    occ = gmsh.model.occ
    a = occ.addBox(0, 0, 0, 2.0, 2.0, 0.5)
    b = occ.addBox(1.0, 1.0, -0.1, 1.1, 1.1, 0.7)
    vol = occ.cut([(3, a)], [(3, b)])[0][0][1]
    occ.synchronize()
    edge = [e for e in _vertical_edges(0.5)
            if np.allclose(gmsh.model.getBoundingBox(1, e)[:2], (1.0, 1.0))]
    occ.fillet([vol], edge, [0.2])


_MAKE = {"plate": _plate, "thin_wall": _thin_wall, "concave_cylinder": _concave_cylinder,
         "reentrant_fillet": _reentrant_fillet}


def folded_patches(geo, samples: int = 11) -> int:
    """Snapped coarse Nagata patches of ``geo`` (3D) whose normal turns against the flat
    facet's somewhere on a ``samples`` x ``samples`` barycentric grid."""
    from nagata_snap.nagata import patch as nagata

    if geo.tdim != 3:
        return 0
    g = np.linspace(0.0, 1.0, samples)
    e, z = np.meshgrid(g, g, indexing="ij")
    lam = np.stack([1 - e, e - z, z], axis=-1)[z <= e]
    sel = np.flatnonzero(geo.snap)
    shape = (sel.size, len(lam))
    xe, xz = nagata.patch_tangents(nagata.patch_coefficients(geo.x[sel], geo.coef[sel]),
                                   np.broadcast_to(1.0 - lam[:, 0], shape),
                                   np.broadcast_to(lam[:, 2], shape))
    n = np.cross(xe, xz)  # oriented like the flat facet's normal; only its sign is used
    fn = np.cross(geo.x[sel, 1] - geo.x[sel, 0], geo.x[sel, 2] - geo.x[sel, 0])
    return int(np.count_nonzero((np.einsum("pki,pi->pk", n, fn) <= 0).any(axis=1)))


def part(comm, name: str):
    """Coarse mesh of part ``name`` (see the module docstring)."""
    return _build(comm, name, _MAKE[name])


#: the part names
PARTS = tuple(_MAKE)


def write_iges(name: str, path: str) -> str:
    """Write part ``name`` as IGES with gmsh/OCC (for CAD mode: ``CadGeometry.from_iges``)."""
    import make_iges

    with generate._gmsh_session(name, False):
        _MAKE[name]()
        gmsh.model.occ.synchronize()
        gmsh.write(path)
    with open(path) as f:
        text = f.read()
    with open(path, "w", newline="\n") as f:
        f.write(make_iges._fix_global(text))
    return path


def from_iges(comm, path: str):
    """Coarse mesh (as the builders) of the solid of an IGES file; one facet tag per face."""

    def build():
        vols, _ = generate.import_iges_solid(path)
        _mesh(vols)

    return generate._build_and_convert(comm, "iges_part", build, 3, msh_file=None, verbose=False,
                                       root=0)


#: facet tags of :func:`touching_hole`
TOUCH_WALLS, TOUCH_HOLE = 1, 5


def touching_hole(comm, n: int = 8, radius: float = 0.1, msh_file: str | None = None):
    """Channel [0, 1] x [0, 0.3] with a hole of radius ``radius`` touching the bottom wall.

    The hole is an ``n``-gon (vertices on the circle, none at the point of
    contact (0.5, 0)), so the chord nearest the wall is ``radius (1 - cos(pi / n))``
    above it and its snapped midpoint lands on the wall (the Nagata curve even
    a little beyond): no valid mesh has it there, the repair must leave it
    short (the last resort, reported).  Tags: walls 1, hole 5.
    """

    def build():
        geo = gmsh.model.geo
        c = geo.addPoint(0.5, radius, 0)
        ang = [math.pi / n + 2 * math.pi * k / n - math.pi / 2 for k in range(n)]
        pts = [geo.addPoint(0.5 + radius * math.cos(a), radius + radius * math.sin(a), 0) for a in ang]
        arcs = [geo.addCircleArc(pts[k], c, pts[(k + 1) % n]) for k in range(n)]
        corners = [geo.addPoint(x, y, 0) for x, y in ((0, 0), (1, 0), (1, 0.3), (0, 0.3))]
        walls = [geo.addLine(corners[k], corners[(k + 1) % 4]) for k in range(4)]
        surf = geo.addPlaneSurface([geo.addCurveLoop(walls), geo.addCurveLoop(arcs)])
        geo.synchronize()
        for a in arcs:
            gmsh.model.mesh.setTransfiniteCurve(a, 2)
        generate._threshold_field(arcs, 1, 0.01, 0.05, 0.2)
        gmsh.model.addPhysicalGroup(2, [surf], generate.VOLUME)
        gmsh.model.addPhysicalGroup(1, walls, TOUCH_WALLS)
        gmsh.model.addPhysicalGroup(1, arcs, TOUCH_HOLE)
        gmsh.model.mesh.generate(2)

    return generate._build_and_convert(comm, "touching_hole", build, 2, msh_file=msh_file,
                                       verbose=False, root=0)
