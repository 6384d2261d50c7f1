"""Reproducible gmsh meshes for the nagata_snap demos and tests.

Every public builder constructs a gmsh model on one MPI rank (``root``,
default 0), converts it with :func:`dolfinx.io.gmsh.model_to_mesh` and
distributes it over ``comm``.  It returns the :class:`dolfinx.io.gmsh.MeshData`
named tuple, so use ``data.mesh``, ``data.cell_tags``, ``data.facet_tags``.
All lengths are in the (dimensionless) units of the geometry, e.g. metres
for the DFG channel.

Determinism: gmsh runs single threaded (``General.NumThreads = 1``) with a
fixed meshing algorithm (``Mesh.Algorithm = 6`` Frontal-Delaunay in 2D,
``Mesh.Algorithm3D = 1`` Delaunay in 3D), mesh sizes come only from the
explicit size fields and transfinite constraints set here (no size from
points, curvature or boundary extension), so the same arguments give the
same mesh, node for node, for a given gmsh version.  gmsh prints nothing
unless ``verbose=True``.  Options changed on an already initialised gmsh
session are restored afterwards.

Tag constants
-------------
DFG channel (:func:`dfg_channel`): ``INLET=1, OUTLET=2, WALLS=3, CYLINDER=4``,
cells ``FLUID=1``.
:func:`sphere_in_box`: ``BOX=1, SPHERE=2`` (cells ``VOLUME=1``).
:func:`ball`: ``BALL_SPHERE=1`` (cells ``VOLUME=1``).
:func:`solid_torus`: ``TORUS_SURFACE=1`` (cells ``VOLUME=1``).
:func:`cylinder_in_box`: ``CIB_WALLS=1`` (all box faces, including the two
faces the hole passes through), ``CIB_CYLINDER=2`` (lateral surface of the
hole) (cells ``VOLUME=1``).
:func:`unit_disk`: ``DISK_BOUNDARY=1`` (cells ``VOLUME=1``).
:func:`iges_solid`: one facet tag per CAD face (its gmsh face tag), cells ``VOLUME=1``.

Run ``python meshes/generate.py`` to write the standard ``.msh`` files
into ``meshes/``.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import typing

import mpi4py.MPI  # noqa: F401  (must precede dolfinx with the PyPI wheel)

import gmsh
import numpy as np

from dolfinx.io import gmsh as _dxgmsh

if os.path.dirname(os.path.dirname(os.path.abspath(__file__))) not in sys.path:  # run as a script
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from nagata_snap.meshing import DETERMINISTIC_OPTIONS, gmsh_session

# --------------------------------------------------------------------------
# Tags
# --------------------------------------------------------------------------
#: DFG 2D-1 facet tags
INLET = 1
OUTLET = 2
WALLS = 3
CYLINDER = 4
#: cell tag of the fluid (DFG) / of the single volume of the 3D meshes
FLUID = 1
VOLUME = 1
#: sphere_in_box facet tags
BOX = 1
SPHERE = 2
#: ball facet tag
BALL_SPHERE = 1
#: solid_torus facet tag
TORUS_SURFACE = 1
#: cylinder_in_box facet tags
CIB_WALLS = 1
CIB_CYLINDER = 2
#: unit_disk facet tag
DISK_BOUNDARY = 1

#: DFG 2D-1 geometry (Schaefer & Turek 1996)
DFG_LENGTH = 2.2
DFG_HEIGHT = 0.41
DFG_CENTER = (0.2, 0.2)
DFG_RADIUS = 0.05

#: Kadir (2010) IGES file 2: cylinder axis along z through (0.55, 0.5),
#: z in [0, 0.4], radius 0.05
KADIR_CYL_CENTER = (0.55, 0.5)
KADIR_CYL_RADIUS = 0.05
KADIR_CYL_BOX = ((0.0, 0.0, 0.0), (1.1, 1.0, 0.4))

MeshData = _dxgmsh.MeshData

_MESHES_DIR = os.path.dirname(os.path.abspath(__file__))


# --------------------------------------------------------------------------
# gmsh session handling
# --------------------------------------------------------------------------
def _fixed_options(verbose: bool) -> dict[str, float]:
    return {
        **DETERMINISTIC_OPTIONS,
        "General.Terminal": 1 if verbose else 0,
        "General.Verbosity": 5 if verbose else 0,
        "Mesh.MeshSizeFromPoints": 0,
        "Mesh.MeshSizeFromCurvature": 0,
        "Mesh.MeshSizeExtendFromBoundary": 0,
        "Mesh.ElementOrder": 1,
        "Mesh.RecombineAll": 0,
        "Mesh.Optimize": 1,
        "Mesh.OptimizeNetgen": 0,
        "Mesh.Smoothing": 1,
        "Mesh.RandomFactor": 1e-9,
        "Mesh.MshFileVersion": 4.1,
        "Mesh.Binary": 0,
    }


@contextlib.contextmanager
def _gmsh_session(name: str, verbose: bool):
    """Open a fresh gmsh model with the fixed options; clean up afterwards."""
    with gmsh_session(name, _fixed_options(verbose)):
        yield gmsh.model


def _build_and_convert(
    comm,
    name: str,
    builder: typing.Callable[[], None],
    gdim: int,
    *,
    msh_file: str | None,
    verbose: bool,
    root: int,
    partitioner=None,
) -> MeshData:
    """Run ``builder`` on rank ``root`` and distribute the mesh over ``comm``.

    ``builder`` creates geometry, physical groups and the mesh in the
    current gmsh model. Errors on ``root`` are broadcast so that no rank
    hangs.  Without an explicit ``partitioner`` DOLFINx's default is used:
    ``GhostMode.none`` (no ghost cells).  Keep it that way for adaptive
    loops that call ``dolfinx.mesh.transfer_meshtag``: in DOLFINx 0.11 that
    function rejects ghosted meshes (FEniCS/dolfinx#3443), and the refined
    mesh must be built with ``refine(..., partitioner=None)`` (the default
    placeholder partitioner adds ghost cells to the child, after which
    ``transfer_meshtag`` corrupts memory in parallel).  Pass
    ``create_cell_partitioner(GhostMode.shared_facet, 2)`` if you need
    interior-facet (``dS``) integrals in parallel.
    """
    if comm.rank == root:
        with _gmsh_session(name, verbose):
            error = None
            try:
                builder()
                if msh_file is not None:
                    gmsh.write(msh_file)
            except Exception as exc:  # pragma: no cover - re-raised below
                error = f"{type(exc).__name__}: {exc}"
            comm.bcast(error, root=root)
            if error is not None:
                raise RuntimeError(f"gmsh failed building '{name}': {error}")
            return _dxgmsh.model_to_mesh(
                gmsh.model, comm, root, gdim=gdim, partitioner=partitioner
            )
    error = comm.bcast(None, root=root)
    if error is not None:
        raise RuntimeError(f"gmsh failed building '{name}' on rank {root}: {error}")
    return _dxgmsh.model_to_mesh(None, comm, root, gdim=gdim, partitioner=partitioner)


# --------------------------------------------------------------------------
# 2D helpers (built-in geo kernel: full control of the circle nodes)
# --------------------------------------------------------------------------
def _split_counts(n: int, n_arcs: int) -> np.ndarray:
    """Segments per arc; for even n (4 arcs) the arc ends include angle pi."""
    if n_arcs == 4 and n % 2 == 0:
        half = n // 2
        a = (half + 1) // 2
        return np.array([a, half - a, a, half - a], dtype=int)
    counts = np.full(n_arcs, n // n_arcs, dtype=int)
    counts[: n % n_arcs] += 1
    return counts


def _geo_circle(xc: float, yc: float, r: float, counts: np.ndarray, centre: int):
    """Closed circle of radius ``r`` as ``len(counts)`` arcs (each < pi).

    Arc k carries ``counts[k]`` segments; arc end points sit at the angles
    ``2 pi * cumsum(counts) / sum(counts)`` so that with uniform transfinite
    constraints all segments of the circle subtend the same angle
    ``2 pi / n`` and a node sits at angle 0 (and at angle pi when n is even).
    Returns (arc tags, point tags).
    """
    geo = gmsh.model.geo
    n = int(counts.sum())
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    angles = 2.0 * np.pi * starts / n
    pts = [geo.addPoint(xc + r * math.cos(a), yc + r * math.sin(a), 0.0) for a in angles]
    arcs = [
        geo.addCircleArc(pts[k], centre, pts[(k + 1) % len(pts)]) for k in range(len(pts))
    ]
    return arcs, pts


def _n_arcs(n: int) -> int:
    if n < 3:
        raise ValueError(f"a circle needs at least 3 segments, got n={n}")
    return 3 if n == 3 else 4


def _threshold_field(curves: list[int], dim: int, h_min: float, h_max: float, dist_max: float):
    """Size field h(d) = h_min + (h_max - h_min) * min(d / dist_max, 1).

    ``d`` is the distance to the given curves (dim=1) or surfaces (dim=2).
    """
    fld = gmsh.model.mesh.field
    dist = fld.add("Distance")
    if dim == 1:
        fld.setNumbers(dist, "CurvesList", curves)
    else:
        fld.setNumbers(dist, "SurfacesList", curves)
    fld.setNumber(dist, "Sampling", 400 if dim == 1 else 60)
    thr = fld.add("Threshold")
    fld.setNumber(thr, "InField", dist)
    fld.setNumber(thr, "SizeMin", h_min)
    fld.setNumber(thr, "SizeMax", h_max)
    fld.setNumber(thr, "DistMin", 0.0)
    fld.setNumber(thr, "DistMax", dist_max)
    fld.setNumber(thr, "Sigmoid", 0)
    fld.setAsBackgroundMesh(thr)


# --------------------------------------------------------------------------
# DFG 2D-1 channel
# --------------------------------------------------------------------------
def dfg_channel(
    comm,
    n_circle: int = 16,
    h_far: float = 0.04,
    boundary_layer: bool = False,
    n_bl: int = 8,
    *,
    h_circle: float | None = None,
    dist_far: float = 0.25,
    bl_first: float = 4.0e-4,
    bl_ratio: float = 1.3,
    bl_arrangement: str = "Left",
    msh_file: str | None = None,
    verbose: bool = False,
    root: int = 0,
    partitioner=None,
) -> MeshData:
    """Triangular mesh of the DFG 2D-1 channel with the cylinder cut out.

    Domain [0, 2.2] x [0, 0.41] minus the disk of radius 0.05 centred at
    (0.2, 0.2) (lengths in m).  The circle is discretised by exactly
    ``n_circle`` straight edges of equal angle 2 pi / n_circle whose vertices
    lie on the true circle, with one vertex at angle 0, i.e. at (0.25, 0.2),
    and for even ``n_circle`` one at (0.15, 0.2) (the pressure-difference
    points).  The mesh size grows linearly with the distance d from the
    circle (or from the outer edge of the boundary layer):
    h(d) = h_c + (h_far - h_c) min(d / dist_far, 1), with h_c the edge
    length on the circle, 2 pi r / n_circle.

    Args:
        comm: MPI communicator the mesh is distributed over.
        n_circle: number of segments on the circle (>= 3).
        h_far: far-field mesh size [m].
        boundary_layer: add a structured ring of ``n_bl`` graded layers
            around the cylinder (quads split into triangles, diagonal
            direction ``bl_arrangement``). First layer thickness
            ``bl_first`` [m], growth ratio ``bl_ratio``.  With the defaults
            the first layer (4e-4 m) is thinner than the sagitta of a
            16-gon edge (9.6e-4 m), so snapping a refined boundary
            midpoint outward without interior smoothing inverts cells.
        n_bl: number of layers in the boundary layer ring.
        h_circle: if given, overrides ``n_circle`` with
            ``max(3, ceil(2 pi r / h_circle))``: regenerate a mesh on the
            true circle at a prescribed boundary size [m].
        dist_far: distance [m] from the circle at which the size reaches
            ``h_far``.
        msh_file: if given, rank ``root`` also writes the gmsh model there.
        verbose: let gmsh print its log.
        root: rank that runs gmsh.
        partitioner: passed to ``model_to_mesh`` (default: DOLFINx's,
            i.e. no ghost cells; see ``_build_and_convert``).

    Returns:
        MeshData with facet tags INLET=1, OUTLET=2, WALLS=3, CYLINDER=4 and
        cell tag FLUID=1.
    """
    xc, yc = DFG_CENTER
    r = DFG_RADIUS
    if h_circle is not None:
        n_circle = max(3, math.ceil(2.0 * math.pi * r / h_circle))
    n = int(n_circle)
    counts = _split_counts(n, _n_arcs(n))
    if boundary_layer:
        if n_bl < 1 or bl_first <= 0.0 or bl_ratio <= 0.0:
            raise ValueError("boundary layer needs n_bl >= 1, bl_first > 0, bl_ratio > 0")
        if abs(bl_ratio - 1.0) < 1e-12:
            thickness = bl_first * n_bl
        else:
            thickness = bl_first * (bl_ratio**n_bl - 1.0) / (bl_ratio - 1.0)
        r_out = r + thickness
        if r_out >= min(yc, DFG_HEIGHT - yc) - 1e-3:
            raise ValueError(f"boundary layer too thick ({thickness:.3g} m)")
    else:
        r_out = r
    h_c = 2.0 * math.pi * r_out / n
    if h_far < h_c:
        h_far = h_c

    def build():
        geo = gmsh.model.geo
        p0 = geo.addPoint(0.0, 0.0, 0.0)
        p1 = geo.addPoint(DFG_LENGTH, 0.0, 0.0)
        p2 = geo.addPoint(DFG_LENGTH, DFG_HEIGHT, 0.0)
        p3 = geo.addPoint(0.0, DFG_HEIGHT, 0.0)
        bottom = geo.addLine(p0, p1)
        outlet = geo.addLine(p1, p2)
        top = geo.addLine(p2, p3)
        inlet = geo.addLine(p3, p0)
        centre = geo.addPoint(xc, yc, 0.0)
        inner_arcs, inner_pts = _geo_circle(xc, yc, r, counts, centre)
        surfaces = []
        if boundary_layer:
            outer_arcs, outer_pts = _geo_circle(xc, yc, r_out, counts, centre)
            radial = [geo.addLine(a, b) for a, b in zip(inner_pts, outer_pts, strict=True)]
            m = len(inner_arcs)
            for k in range(m):
                loop = geo.addCurveLoop(
                    [inner_arcs[k], radial[(k + 1) % m], -outer_arcs[k], -radial[k]]
                )
                surfaces.append(geo.addPlaneSurface([loop]))
            hole_arcs = outer_arcs
        else:
            hole_arcs = inner_arcs
        outer_loop = geo.addCurveLoop([bottom, outlet, top, inlet])
        hole_loop = geo.addCurveLoop(hole_arcs)
        fluid = geo.addPlaneSurface([outer_loop, hole_loop])
        geo.synchronize()

        mesh = gmsh.model.mesh
        for arc, c in zip(inner_arcs, counts, strict=True):
            mesh.setTransfiniteCurve(arc, int(c) + 1)
        if boundary_layer:
            for arc, c in zip(outer_arcs, counts, strict=True):
                mesh.setTransfiniteCurve(arc, int(c) + 1)
            for line in radial:
                mesh.setTransfiniteCurve(line, n_bl + 1, "Progression", bl_ratio)
            for k, s in enumerate(surfaces):
                corners = [
                    inner_pts[k],
                    inner_pts[(k + 1) % len(inner_pts)],
                    outer_pts[(k + 1) % len(outer_pts)],
                    outer_pts[k],
                ]
                mesh.setTransfiniteSurface(s, bl_arrangement, corners)
        _threshold_field(hole_arcs, 1, h_c, h_far, dist_far)

        gmsh.model.addPhysicalGroup(2, [fluid, *surfaces], FLUID, name="fluid")
        gmsh.model.addPhysicalGroup(1, [inlet], INLET, name="inlet")
        gmsh.model.addPhysicalGroup(1, [outlet], OUTLET, name="outlet")
        gmsh.model.addPhysicalGroup(1, [bottom, top], WALLS, name="walls")
        gmsh.model.addPhysicalGroup(1, inner_arcs, CYLINDER, name="cylinder")
        mesh.generate(2)

    name = f"dfg_n{n}{'_bl' if boundary_layer else ''}"
    return _build_and_convert(
        comm, name, build, 2, msh_file=msh_file, verbose=verbose, root=root,
        partitioner=partitioner,
    )


def dfg_channel_regenerated(
    comm,
    level: int,
    n_circle: int = 16,
    h_far: float = 0.04,
    **kwargs,
) -> MeshData:
    """DFG mesh regenerated on the true circle at refinement ``level``.

    Equivalent in size to ``level`` uniform refinements of
    ``dfg_channel(comm, n_circle, h_far)``: the circle gets
    ``n_circle * 2**level`` segments (vertices on the true circle) and the
    far-field size is ``h_far / 2**level``, with the same grading distance.
    This produces the "regenerated-mesh" reference curve that snapped
    adaptive refinement should track.  Extra keyword arguments go to
    :func:`dfg_channel`.
    """
    if level < 0:
        raise ValueError("level must be >= 0")
    return dfg_channel(
        comm, n_circle=n_circle * 2**level, h_far=h_far / 2**level, **kwargs
    )


# --------------------------------------------------------------------------
# unit disk
# --------------------------------------------------------------------------
def unit_disk(
    comm,
    n: int = 16,
    *,
    radius: float = 1.0,
    h: float | None = None,
    msh_file: str | None = None,
    verbose: bool = False,
    root: int = 0,
    partitioner=None,
) -> MeshData:
    """Triangular mesh of the disk of radius ``radius`` centred at the origin.

    The boundary circle has exactly ``n`` equal segments (vertices on the
    circle, one at angle 0); the interior size is ``h`` (default: the
    boundary edge length 2 pi radius / n).

    Returns:
        MeshData with facet tag DISK_BOUNDARY=1 and cell tag VOLUME=1.
    """
    counts = _split_counts(int(n), _n_arcs(int(n)))
    h_b = 2.0 * math.pi * radius / n
    h_in = h_b if h is None else h

    def build():
        geo = gmsh.model.geo
        centre = geo.addPoint(0.0, 0.0, 0.0)
        arcs, _ = _geo_circle(0.0, 0.0, radius, counts, centre)
        loop = geo.addCurveLoop(arcs)
        surf = geo.addPlaneSurface([loop])
        geo.synchronize()
        for arc, c in zip(arcs, counts, strict=True):
            gmsh.model.mesh.setTransfiniteCurve(arc, int(c) + 1)
        _threshold_field(arcs, 1, h_b, h_in, max(radius, 1e-12))
        gmsh.model.addPhysicalGroup(2, [surf], VOLUME, name="disk")
        gmsh.model.addPhysicalGroup(1, arcs, DISK_BOUNDARY, name="boundary")
        gmsh.model.mesh.generate(2)

    return _build_and_convert(
        comm, f"unit_disk_n{n}", build, 2, msh_file=msh_file, verbose=verbose,
        root=root, partitioner=partitioner,
    )


# --------------------------------------------------------------------------
# 3D meshes (OpenCASCADE kernel)
# --------------------------------------------------------------------------
def _boundary_surfaces(volumes: list[tuple[int, int]]) -> list[int]:
    return [
        s for _, s in gmsh.model.getBoundary(volumes, combined=True, oriented=False)
    ]


def _surfaces_of_type(surfaces: list[int], kind: str) -> list[int]:
    return [s for s in surfaces if gmsh.model.getType(2, s) == kind]


def _box_minus_tool(lo, hi, make_tool, curved_type: str, h_curved: float, h_box: float,
                    dist: float, box_group: tuple[int, str], curved_group: tuple[int, str]) -> None:
    """Mesh (in the current gmsh model) the box ``[lo, hi]`` minus an OCC tool solid.

    ``make_tool(occ) -> tag`` adds the tool after the box; its faces of OCC
    type ``curved_type`` ("Sphere", "Cylinder") get size ``h_curved``, growing
    to ``h_box`` at distance ``dist``; physical groups: the volume, the other
    faces (``box_group``) and the curved faces (``curved_group``).
    """
    occ = gmsh.model.occ
    b = occ.addBox(*lo, *(hi - lo))
    tool = make_tool(occ)
    out, _ = occ.cut([(3, b)], [(3, tool)])
    occ.synchronize()
    vols = [t for d, t in out if d == 3]
    surfs = _boundary_surfaces([(3, v) for v in vols])
    curved = _surfaces_of_type(surfs, curved_type)
    rest = [t for t in surfs if t not in curved]
    _threshold_field(curved, 2, h_curved, max(h_box, h_curved), dist)
    gmsh.model.addPhysicalGroup(3, vols, VOLUME, name="volume")
    gmsh.model.addPhysicalGroup(2, rest, box_group[0], name=box_group[1])
    gmsh.model.addPhysicalGroup(2, curved, curved_group[0], name=curved_group[1])
    gmsh.model.mesh.generate(3)


def sphere_in_box(
    comm,
    radius: float = 0.5,
    box: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (-1.0, -1.0, -1.0),
        (1.0, 1.0, 1.0),
    ),
    h_sphere: float = 0.15,
    h_box: float = 0.4,
    *,
    center: tuple[float, float, float] = (0.0, 0.0, 0.0),
    dist_far: float | None = None,
    msh_file: str | None = None,
    verbose: bool = False,
    root: int = 0,
    partitioner=None,
) -> MeshData:
    """Tetrahedral mesh of ``box`` minus the ball of ``radius`` at ``center``.

    ``box`` is ((xmin, ymin, zmin), (xmax, ymax, zmax)).  Size ``h_sphere``
    on the sphere growing linearly to ``h_box`` at distance ``dist_far``
    (default: the smallest sphere-to-box gap).

    Returns:
        MeshData with facet tags BOX=1 (the six box faces), SPHERE=2 and
        cell tag VOLUME=1.
    """
    lo = np.asarray(box[0], dtype=float)
    hi = np.asarray(box[1], dtype=float)
    c = np.asarray(center, dtype=float)
    gap = float(min((c - lo).min(), (hi - c).min()) - radius)
    if gap <= 0.0:
        raise ValueError("sphere must lie strictly inside the box")
    dmax = gap if dist_far is None else dist_far

    def build():
        _box_minus_tool(lo, hi, lambda occ: occ.addSphere(*c, radius), "Sphere",
                        h_sphere, h_box, dmax, (BOX, "box"), (SPHERE, "sphere"))

    return _build_and_convert(
        comm, "sphere_in_box", build, 3, msh_file=msh_file, verbose=verbose,
        root=root, partitioner=partitioner,
    )


def squeeze_wall_layer(mesh, radius: float = 0.5, reach: float = 0.3, factor: float = 0.15) -> None:
    """Squeeze the cells off a sphere into a thin near-wall layer (in place).

    Every geometry node at a distance ``0 < r - radius < reach`` from the
    origin is moved radially to ``radius + factor (r - radius)``: the first
    cell layer off the sphere becomes ``factor`` times thinner, so that
    snapping the sphere's new vertices outwards inverts cells (the hard 3D
    case of the smoothing tests and ``benchmarks/hard_cases.py``).
    """
    x = mesh.geometry.x
    r = np.linalg.norm(x, axis=1)
    sel = (r > radius + 1e-9) & (r < radius + reach)
    x[sel] *= ((radius + factor * (r[sel] - radius)) / r[sel])[:, None]


def _constant_size(h: float) -> None:
    """Uniform mesh size ``h``: a constant background field."""
    fld = gmsh.model.mesh.field
    f = fld.add("MathEval")
    fld.setString(f, "F", repr(float(h)))
    fld.setAsBackgroundMesh(f)


def _mesh_solid(add_solid: typing.Callable[[], int], h: float, tag: int, name: str) -> None:
    """Tetrahedra of size ``h`` in the one OCC solid ``add_solid()`` makes (its volume tag):
    cell tag VOLUME, its boundary surfaces facet tag ``tag`` (physical name ``name``)."""
    vol = add_solid()
    gmsh.model.occ.synchronize()
    _constant_size(h)
    gmsh.model.addPhysicalGroup(3, [vol], VOLUME, name="volume")
    gmsh.model.addPhysicalGroup(2, _boundary_surfaces([(3, vol)]), tag, name=name)
    gmsh.model.mesh.generate(3)


def ball(
    comm,
    radius: float = 1.0,
    h: float = 0.3,
    *,
    center: tuple[float, float, float] = (0.0, 0.0, 0.0),
    msh_file: str | None = None,
    verbose: bool = False,
    root: int = 0,
    partitioner=None,
) -> MeshData:
    """Tetrahedral mesh of the ball of ``radius`` at ``center``, uniform size ``h``.

    Returns:
        MeshData with facet tag BALL_SPHERE=1 and cell tag VOLUME=1.
    """

    def build():
        _mesh_solid(lambda: gmsh.model.occ.addSphere(*center, radius), h, BALL_SPHERE, "sphere")

    return _build_and_convert(
        comm, "ball", build, 3, msh_file=msh_file, verbose=verbose, root=root,
        partitioner=partitioner,
    )


def solid_torus(
    comm,
    major_radius: float = 1.0,
    minor_radius: float = 0.5,
    h: float = 0.3,
    *,
    msh_file: str | None = None,
    verbose: bool = False,
    root: int = 0,
    partitioner=None,
) -> MeshData:
    """Tetrahedral mesh of the solid torus about the z axis, centre at the origin, size ``h``.

    Volume ``2 pi^2 major_radius minor_radius^2``; its surface has two
    different principal curvatures (unlike the ball's sphere).

    Returns:
        MeshData with facet tag TORUS_SURFACE=1 and cell tag VOLUME=1.
    """

    def build():
        _mesh_solid(lambda: gmsh.model.occ.addTorus(0.0, 0.0, 0.0, major_radius, minor_radius), h,
                    TORUS_SURFACE, "torus")

    return _build_and_convert(
        comm, "solid_torus", build, 3, msh_file=msh_file, verbose=verbose, root=root,
        partitioner=partitioner,
    )


def cylinder_in_box(
    comm,
    radius: float = KADIR_CYL_RADIUS,
    center: tuple[float, float] = KADIR_CYL_CENTER,
    box: tuple[tuple[float, float, float], tuple[float, float, float]] = KADIR_CYL_BOX,
    h_cylinder: float = 0.02,
    h_box: float = 0.1,
    *,
    dist_far: float = 0.3,
    msh_file: str | None = None,
    verbose: bool = False,
    root: int = 0,
    partitioner=None,
) -> MeshData:
    """Tetrahedral mesh of a box with a cylindrical hole along z through it.

    Defaults follow Kadir (2010), IGES file 2: axis through (0.55, 0.5),
    z from 0 to 0.4, radius 0.05, in the box [0, 1.1] x [0, 1] x [0, 0.4];
    the hole passes through the faces z = zmin and z = zmax.  Size
    ``h_cylinder`` on the lateral surface growing linearly to ``h_box`` at
    distance ``dist_far``.

    Returns:
        MeshData with facet tags CIB_WALLS=1 (all box faces), CIB_CYLINDER=2
        (lateral surface of the hole) and cell tag VOLUME=1.
    """
    lo = np.asarray(box[0], dtype=float)
    hi = np.asarray(box[1], dtype=float)
    xc, yc = center
    if not (lo[0] < xc - radius and xc + radius < hi[0] and lo[1] < yc - radius
            and yc + radius < hi[1]):
        raise ValueError("cylinder must lie strictly inside the box in x and y")

    def build():
        extra = 0.1 * (hi[2] - lo[2])
        _box_minus_tool(
            lo, hi,
            lambda occ: occ.addCylinder(xc, yc, lo[2] - extra, 0.0, 0.0,
                                        hi[2] - lo[2] + 2 * extra, radius),
            "Cylinder", h_cylinder, h_box, dist_far, (CIB_WALLS, "walls"),
            (CIB_CYLINDER, "cylinder"))

    return _build_and_convert(
        comm, "cylinder_in_box", build, 3, msh_file=msh_file, verbose=verbose,
        root=root, partitioner=partitioner,
    )


#: healing tolerance used by :func:`import_iges_solid` (length units of the file)
IGES_HEAL_TOLERANCE = 1e-4


def import_iges_solid(path: str, heal_tolerance: float = IGES_HEAL_TOLERANCE) -> tuple[list[int], list[int]]:
    """Import an IGES file into the current gmsh model (OCC) as one solid.

    IGES carries faces, not solids: the faces are sewn and made a solid with
    ``gmsh.model.occ.healShapes``.  OCC re-reading its own IGES gives the
    faces of revolution model-space boundary curves ~1e-5 off their
    neighbours' (e.g. ``occ_part.igs``: the hole's circles), so the default
    sewing tolerance leaves them unsewn; ``heal_tolerance`` (1e-4) joins them.
    Sewing changes the topology only: the face surfaces stay the file's.

    Returns:
        ``(volume tags, face tags)`` of the model after synchronisation.

    Raises:
        RuntimeError: no solid could be made.
    """
    occ = gmsh.model.occ
    occ.importShapes(path)
    occ.synchronize()
    if not gmsh.model.getEntities(3):
        occ.healShapes([], tolerance=heal_tolerance, sewFaces=True, makeSolids=True)
        occ.synchronize()
    if not gmsh.model.getEntities(3):  # sewn but not made a solid: close the shell
        occ.addVolume([occ.addSurfaceLoop([t for _, t in gmsh.model.getEntities(2)])])
        occ.synchronize()
    vols = [t for _, t in gmsh.model.getEntities(3)]
    if not vols:
        raise RuntimeError(f"{path}: the IGES faces do not close into a solid "
                           f"(sewing tolerance {heal_tolerance:g})")
    return vols, _boundary_surfaces([(3, v) for v in vols])


def _mesh_uniform_per_face(vols: list[int], faces: list[int], h: float) -> None:
    """Tetrahedra of uniform size ``h`` in ``vols``; physical group = face tag for every face."""
    fld = gmsh.model.mesh.field
    f = fld.add("MathEval")
    fld.setString(f, "F", repr(float(h)))
    fld.setAsBackgroundMesh(f)
    gmsh.model.addPhysicalGroup(3, vols, VOLUME, name="volume")
    for t in faces:  # loop over CAD faces (a few), one physical group each
        gmsh.model.addPhysicalGroup(2, [t], t, name=f"face{t}")
    gmsh.model.mesh.generate(3)


def iges_solid(
    comm,
    path: str,
    h: float = 0.2,
    *,
    heal_tolerance: float = IGES_HEAL_TOLERANCE,
    msh_file: str | None = None,
    verbose: bool = False,
    root: int = 0,
    partitioner=None,
) -> MeshData:
    """Tetrahedral mesh, uniform size ``h``, of the solid bounded by an IGES file's faces.

    The file is imported with :func:`import_iges_solid` (OCC kernel), e.g.
    ``meshes/occ_part.igs`` (box with a cylindrical hole).

    Returns:
        MeshData with one facet tag per CAD face, equal to the gmsh face tag
        (the faces in the file's order: ``1..n``), and cell tag VOLUME=1.
    """

    def build():
        _mesh_uniform_per_face(*import_iges_solid(path, heal_tolerance), h)

    return _build_and_convert(
        comm, "iges_solid", build, 3, msh_file=msh_file, verbose=verbose, root=root,
        partitioner=partitioner,
    )


def occ_features(
    comm,
    h: float = 0.1,
    *,
    msh_file: str | None = None,
    verbose: bool = False,
    root: int = 0,
    partitioner=None,
) -> MeshData:
    """Tetrahedral mesh, uniform size ``h``, of ``make_iges.build_occ_features``'s part.

    Built from the OCC construction itself (the model ``write_occ_features``
    writes to IGES): OCC re-reading that IGES gives a shell gmsh cannot fill
    with tetrahedra.

    Returns:
        MeshData with one facet tag per face (its gmsh face tag), cells VOLUME=1.
    """
    import make_iges

    def build():
        vols = make_iges.build_occ_features()
        _mesh_uniform_per_face(vols, _boundary_surfaces([(3, v) for v in vols]), h)

    return _build_and_convert(
        comm, "occ_features", build, 3, msh_file=msh_file, verbose=verbose, root=root,
        partitioner=partitioner,
    )


# --------------------------------------------------------------------------
# standard files
# --------------------------------------------------------------------------
def write_standard_meshes(comm=None, directory: str = _MESHES_DIR) -> list[str]:
    """Write the standard demo/test meshes as gmsh .msh 4.1 files.

    Returns the list of paths written (on every rank).
    """
    from mpi4py import MPI

    comm = MPI.COMM_SELF if comm is None else comm
    jobs = [
        ("dfg_n16.msh", lambda f: dfg_channel(comm, 16, msh_file=f)),
        ("dfg_n8.msh", lambda f: dfg_channel(comm, 8, h_far=0.06, msh_file=f)),
        ("dfg_n16_bl.msh", lambda f: dfg_channel(comm, 16, boundary_layer=True, msh_file=f)),
        ("unit_disk_n16.msh", lambda f: unit_disk(comm, 16, msh_file=f)),
        ("sphere_in_box.msh", lambda f: sphere_in_box(comm, msh_file=f)),
        ("ball.msh", lambda f: ball(comm, msh_file=f)),
        ("cylinder_in_box.msh", lambda f: cylinder_in_box(comm, msh_file=f)),
    ]
    paths = []
    for fname, job in jobs:
        path = os.path.join(directory, fname)
        data = job(path)
        ncells = data.mesh.topology.index_map(data.mesh.topology.dim).size_global
        if comm.rank == 0:
            print(f"{path}: {ncells} cells")
        paths.append(path)
    return paths


if __name__ == "__main__":
    write_standard_meshes()
