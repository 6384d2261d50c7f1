"""Curved geometry of degree k from the lineage: orders, node placement, blending, Jacobians, MPI."""

import os
import subprocess
import sys

import basix
import numpy as np
import pytest
import ufl
from mpi4py import MPI
from scipy.spatial import cKDTree

import dolfinx.fem as fem
import dolfinx.fem.petsc
import dolfinx.mesh as dmesh
import generate
import make_iges

from nagata_snap import NagataGeometry, Snapper
from nagata_snap.cad import CadGeometry
from nagata_snap.curved import jacobian_determinants
from nagata_snap.cad.nurbs import circle, sphere

HERE = os.path.dirname(__file__)


def measure(m, degree=2):
    dx = ufl.dx(domain=m, metadata={"quadrature_degree": 2 * degree})
    return m.comm.allreduce(fem.assemble_scalar(fem.form(fem.Constant(m, 1.0) * dx)))


def orders(errors):
    e = np.asarray(errors)
    return np.log2(e[:-1] / e[1:])


def cell_type(tdim):
    return basix.CellType.triangle if tdim == 2 else basix.CellType.tetrahedron


def dense_jacobian_ratios(cm, k, variant):
    """det J / det J_straight at a degree-(2k+6) quadrature (not the guard's check points)."""
    tdim = cm.topology.dim
    el = basix.create_element(basix.ElementFamily.P, cell_type(tdim), k, basix.LagrangeVariant[variant])
    q, _ = basix.make_quadrature(cell_type(tdim), 2 * k + 6)
    dphi = el.tabulate(1, q)[1 : tdim + 1, :, :, 0]
    cells = cm.geometry.dofmaps[0][: cm.topology.index_map(tdim).size_local]
    X = cm.geometry.x[cells][:, :, :tdim]
    det = np.linalg.det(np.einsum("cki,dqk->cqid", X, dphi))
    v = X[:, : tdim + 1]
    det0 = np.linalg.det(np.stack([v[:, i + 1] - v[:, 0] for i in range(tdim)], axis=-1))
    return det / det0[:, None]


def boundary_nodes(cm, facets):
    tdim = cm.topology.dim
    cm.topology.create_connectivity(tdim - 1, tdim)
    return np.unique(dmesh.entities_to_geometry(cm, tdim - 1, facets))


def straight_nodes(mesh, cm):
    """Node positions of the straight mesh in the coordinate element of ``cm`` (DOLFINx)."""
    cmap = cm.geometry.cmaps[0]
    ce = fem.coordinate_element(mesh.topology.cell_type, cmap.degree, cmap.variant)
    return fem.interpolate_geometry(mesh, ce).geometry.x


def disk_snapper():
    md = generate.unit_disk(MPI.COMM_WORLD, n=16)
    s = Snapper(md.mesh, md.facet_tags, CadGeometry([circle((0.0, 0.0, 0.0), 1.0)]),
                tags=[generate.DISK_BOUNDARY])
    return md.mesh, md.facet_tags, s


# (degree, variant, expected order of the area error of the disk, CAD circle):
# the area of a curved edge's interpolant is the interpolatory quadrature of
# its nodes; Gauss-Lobatto nodes (gll_warped) make it exact to degree 2k - 1,
# so the order is 2k; equispaced nodes integrate degree k+1 exactly only for even k.
AREA_CASES = [(2, "equispaced", 4), (3, "equispaced", 4), (3, "gll_warped", 6), (4, "gll_warped", 8)]


@pytest.mark.parametrize("k,variant,order", AREA_CASES)
def test_disk_area_and_perimeter_orders(k, variant, order):
    mesh, ft, snapper = disk_snapper()
    area, length = [], []
    for level in range(3):
        if level:
            mesh, ft, *_ = snapper.refine(mesh)
        cm, info = snapper.curved_mesh(degree=k, variant=variant)
        assert cm.geometry.cmaps[0].degree == k
        assert basix.LagrangeVariant(cm.geometry.cmaps[0].variant).name == variant
        assert cm.topology._cpp_object is mesh.topology._cpp_object  # tags and parent maps apply
        assert info.reduced_nodes == 0 and info.min_jacobian_ratio > 0.5
        assert info.boundary_nodes == (k - 1) * 16 * 2**level  # every non-vertex node of the circle
        area.append(abs(measure(cm, k) - np.pi))
        ds = ufl.Measure("ds", domain=cm, subdomain_data=ft, metadata={"quadrature_degree": 2 * k})
        length.append(abs(cm.comm.allreduce(fem.assemble_scalar(fem.form(
            fem.Constant(cm, 1.0) * ds(generate.DISK_BOUNDARY)))) - 2 * np.pi))
    o = orders(area)
    assert np.all((o > order - 0.3) & (o < order + 0.5)), o  # (+0.5: round-off at 1e-13)
    assert np.all(orders(length) > k + 0.7), orders(length)  # the perimeter: at least k+1


@pytest.mark.parametrize("k,order", [(3, 4), (4, 6)])
def test_ball_volume_order(k, order):
    """Ball (CAD sphere): order k+1 for k = 3; k+2 for k = 4 (the sphere's offset is even)."""
    md = generate.ball(MPI.COMM_WORLD, radius=1.0, h=0.5)
    mesh, ft = md.mesh, md.facet_tags
    snapper = Snapper(mesh, ft, CadGeometry([sphere((0.0, 0.0, 0.0), 1.0)]),
                      tags=[generate.BALL_SPHERE])
    err = []
    for level in range(3):
        if level:
            mesh, ft, *_ = snapper.refine(mesh)
        cm, info = snapper.curved_mesh(degree=k)
        assert info.min_jacobian_ratio > 0.3 and info.blended_nodes > 0
        err.append(abs(measure(cm, k) - 4 / 3 * np.pi))
    assert abs(orders(err)[-1] - order) < 0.15, orders(err)  # the first pair is pre-asymptotic


@pytest.mark.parametrize("tdim,k", [(2, 3), (2, 4), (3, 3), (3, 4)])
def test_cad_nodes_are_closest_points_of_their_straight_position(tdim, k):
    """Every node of a snapped facet is the closest point on the circle / sphere of its
    straight position (the projection the CAD Newton converges to); vertices unchanged."""
    if tdim == 2:
        mesh, ft, snapper = disk_snapper()
        tag = generate.DISK_BOUNDARY
    else:
        md = generate.ball(MPI.COMM_WORLD, radius=1.0, h=0.6)
        mesh, ft = md.mesh, md.facet_tags
        tag = generate.BALL_SPHERE
        snapper = Snapper(mesh, ft, CadGeometry([sphere((0.0, 0.0, 0.0), 1.0)]), tags=[tag])
    mesh, ft, *_ = snapper.refine(mesh)
    cm, info = snapper.curved_mesh(degree=k)
    nodes = boundary_nodes(cm, ft.find(tag))
    x, x0 = cm.geometry.x[nodes], straight_nodes(mesh, cm)[nodes]
    assert np.abs(np.linalg.norm(x, axis=1) - 1.0).max() < 1e-12
    assert np.abs(x - x0 / np.linalg.norm(x0, axis=1)[:, None]).max() < 1e-12
    n_nonvertex = len(nodes) - len(boundary_nodes(mesh, ft.find(tag)))
    assert info.boundary_nodes == n_nonvertex
    # vertices exactly where snapping put them
    assert np.array_equal(cm.geometry.x[cm.geometry.dofmaps[0][:, : tdim + 1]],
                          mesh.geometry.x[mesh.geometry.dofmaps[0]])


@pytest.mark.parametrize("case", ["dfg", "ball"])
def test_nagata_nodes_lie_on_the_patch_at_their_barycentric_position(case):
    """The Nagata patch is quadratic, so the degree-2 mesh reproduces it; the nodes of the
    degree-3 and 4 boundary facets must be the degree-2 map at their reference positions."""
    if case == "dfg":
        md = generate.dfg_channel(MPI.COMM_WORLD, n_circle=16, h_far=0.1)
        tag = generate.CYLINDER
    else:
        md = generate.ball(MPI.COMM_WORLD, radius=1.0, h=0.6)
        tag = generate.BALL_SPHERE
    mesh, ft = md.mesh, md.facet_tags
    snapper = Snapper(mesh, ft, NagataGeometry(mesh, ft, tags=[tag]))
    mesh, ft, *_ = snapper.refine(mesh)
    tdim = mesh.topology.dim
    c2, _ = snapper.curved_mesh(degree=2)
    p2 = basix.create_element(basix.ElementFamily.P, cell_type(tdim), 2, basix.LagrangeVariant.equispaced)
    mesh.topology.create_connectivity(tdim - 1, tdim)
    f2c = mesh.topology.connectivity(tdim - 1, tdim)
    c2f = mesh.topology.connectivity(tdim, tdim - 1)
    facets = ft.find(tag)
    cells = np.array([f2c.links(f)[0] for f in facets])
    local = np.array([list(c2f.links(c)).index(f) for c, f in zip(cells, facets, strict=True)])
    for k in (3, 4):
        ck, _ = snapper.curved_mesh(degree=k)
        el = basix.create_element(basix.ElementFamily.P, cell_type(tdim), k, basix.LagrangeVariant.gll_warped)
        phi = p2.tabulate(0, el.points)[0, :, :, 0]  # (ndofs_k, 6 or 10)
        pred = np.einsum("pn,cni->cpi", phi, c2.geometry.x[c2.geometry.dofmaps[0][cells]])
        xk = ck.geometry.x[ck.geometry.dofmaps[0][cells]]
        for lf in range(tdim + 1):
            on = local == lf
            cl = el.entity_closure_dofs[tdim - 1][lf]
            assert np.abs(xk[on][:, cl] - pred[on][:, cl]).max(initial=0.0) < 1e-13
        # and the domain is the same (boundary unchanged by the degree)
        assert measure(ck, k) == pytest.approx(measure(c2, 2), rel=1e-12)


def _dfg_boundary_layer():
    md = generate.dfg_channel(MPI.COMM_WORLD, n_circle=8, boundary_layer=True)
    mesh, ft = md.mesh, md.facet_tags
    return mesh, Snapper(mesh, ft, NagataGeometry(mesh, ft, tags=[generate.CYLINDER]))


@pytest.mark.parametrize("k", [2, 3, 4])
def test_jacobian_guard_pulls_back_crushing_nodes(k):
    """Boundary-layer cells thinner than the 8-gon's sagitta: nodes are pulled back
    (reported) until det J > 0 everywhere, checked at points the guard does not use."""
    _, snapper = _dfg_boundary_layer()
    cm, info = snapper.curved_mesh(degree=k, min_ratio=0.05)
    assert info.reduced_nodes > 0 and info.max_shortfall > 0
    assert info.min_jacobian_ratio >= 0.05
    variant = info.variant
    assert dense_jacobian_ratios(cm, k, variant).min() > 0.0
    cells = cm.geometry.dofmaps[0][: cm.topology.index_map(2).size_local]
    det = jacobian_determinants(cm.geometry.x, cells, 2, variant)
    assert np.all(np.sign(det) == np.sign(det[:, :1]))  # no sign change inside any cell


def test_blending_keeps_strongly_curved_cells_valid():
    """Interior nodes left straight would invert cells that the blended ones keep valid."""
    mesh, snapper = _dfg_boundary_layer()
    cm, info = snapper.curved_mesh(degree=4)
    assert info.blended_nodes > 0
    r = dense_jacobian_ratios(cm, 4, info.variant)
    x = cm.geometry.x
    tdim = 2
    mesh.topology.create_connectivity(tdim - 1, tdim)
    keep = np.zeros(len(x), dtype=bool)
    keep[boundary_nodes(cm, dmesh.exterior_facet_indices(mesh.topology))] = True
    x[~keep] = straight_nodes(mesh, cm)[~keep]  # un-blend
    r_straight = dense_jacobian_ratios(cm, 4, info.variant)
    assert r.min() > 0.3
    assert r_straight.min() < 0.0


def test_blending_in_3d_beats_straight_interior():
    md = generate.ball(MPI.COMM_WORLD, radius=1.0, h=1.0)
    snapper = Snapper(md.mesh, md.facet_tags, CadGeometry([sphere((0.0, 0.0, 0.0), 1.0)]),
                      tags=[generate.BALL_SPHERE])
    cm, info = snapper.curved_mesh(degree=3)
    assert info.blended_nodes > 0 and info.reduced_nodes == 0
    r = dense_jacobian_ratios(cm, 3, info.variant)
    x = cm.geometry.x
    mesh = md.mesh
    mesh.topology.create_connectivity(2, 3)
    keep = np.zeros(len(x), dtype=bool)
    keep[boundary_nodes(cm, dmesh.exterior_facet_indices(mesh.topology))] = True
    x[~keep] = straight_nodes(mesh, cm)[~keep]
    assert r.min() > 0.9 > 0.7 > dense_jacobian_ratios(cm, 3, info.variant).min()


def poisson_l2_error(m, k):
    """P_k solution of -Lap u = f, u = 0 on the boundary, u = cos(pi r^2 / 2); L2 error."""
    x = ufl.SpatialCoordinate(m)
    u_ex = ufl.cos(ufl.pi * ufl.inner(x, x) / 2)
    f = -ufl.div(ufl.grad(u_ex))
    V = fem.functionspace(m, ("Lagrange", k))
    tdim = m.topology.dim
    m.topology.create_connectivity(tdim - 1, tdim)
    dofs = fem.locate_dofs_topological(V, tdim - 1, dmesh.exterior_facet_indices(m.topology))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    dx = ufl.dx(metadata={"quadrature_degree": 2 * k + 2})
    problem = dolfinx.fem.petsc.LinearProblem(
        ufl.inner(ufl.grad(u), ufl.grad(v)) * dx, f * v * dx, bcs=[fem.dirichletbc(0.0, dofs, V)],
        petsc_options_prefix=f"curved_p{k}_", petsc_options={"ksp_type": "preonly", "pc_type": "lu"})
    uh = problem.solve()
    uh = uh[0] if isinstance(uh, tuple) else uh
    e = fem.assemble_scalar(fem.form((uh - u_ex) ** 2 * dx))
    return float(np.sqrt(m.comm.allreduce(e)))


def test_poisson_p3_on_cubic_disk_converges_at_order_4():
    mesh, _, snapper = disk_snapper()
    curved, straight = [], []
    for level in range(3):
        if level:
            mesh, *_ = snapper.refine(mesh)
        cm, _ = snapper.curved_mesh(degree=3)
        curved.append(poisson_l2_error(cm, 3))
        straight.append(poisson_l2_error(mesh, 3))
    assert orders(curved)[-1] > 3.7, orders(curved)
    assert abs(orders(straight)[-1] - 2) < 0.3  # straight cells: the domain error
    assert curved[-1] < 1e-3 * straight[-1]


@pytest.mark.parametrize("kwargs,match", [
    ({"degree": 1}, "degree must be an integer from 2 to 6"),
    ({"degree": 7}, "degree must be an integer from 2 to 6"),
    ({"degree": 2.5}, "degree must be an integer"),
    ({"degree": 3, "variant": "legendre"}, "variant must be one of"),
    ({"degree": 3, "min_ratio": 1.0}, "min_ratio must be in"),
])
def test_bad_arguments(kwargs, match):
    _, _, snapper = disk_snapper()
    with pytest.raises(ValueError, match=match):
        snapper.curved_mesh(**kwargs)


def _run_curved(n, args, tmp_path):
    out = tmp_path / f"curved_{n}_{'_'.join(args)}.npz"
    exe = [os.path.join(os.path.dirname(sys.executable), "mpiexec"), "-n", str(n)] if n > 1 else []
    r = subprocess.run([*exe, sys.executable, os.path.join(HERE, "mpi", "curved.py"), *args, str(out)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return np.load(out)


@pytest.mark.mpi
@pytest.mark.parametrize("args", [("dfg_nagata", "2", "3"), ("dfg_nagata", "1", "4"), ("ball_cad", "1", "3"),
                                  ("ball_cad", "1", "4")])
def test_curved_mpi_matches_serial(args, tmp_path):
    """Under mpiexec -n 2 every node of the curved mesh (boundary, blended, interior) is where
    the serial run puts it, and area / volume and the boundary counts agree.  (3D: uniform
    refinement cuts inner octahedra along partition-dependent diagonals, so nodes are
    matched by their straight positions: those of the edges, faces and cells both runs have.)"""
    serial, par = _run_curved(1, args, tmp_path), _run_curved(2, args, tmp_path)
    assert serial["counts"][0] == par["counts"][0]  # boundary nodes
    assert float(par["measure"]) == pytest.approx(float(serial["measure"]), rel=1e-13)
    assert serial["x"].shape == par["x"].shape
    d, i = cKDTree(par["x0"]).query(serial["x0"])
    same = d < 1e-12
    assert same.mean() > (0.999 if args[0].startswith("dfg") else 0.8)
    assert np.abs(serial["x"][same] - par["x"][i[same]]).max() < 1e-12


def test_cad_part_edge_and_face_nodes_on_their_faces(tmp_path):
    """OCC part (box minus a cylindrical hole, 7 trimmed faces): every node of the degree-3
    boundary facets is on its face (planes flat, the hole's wall at r = 0.2), so the nodes of
    the rim edges are on both faces: the CAD edge (the curved-edge rule of ``place``)."""
    import warnings

    paths = make_iges.write_occ_models(tmp_path)
    part = str(next(p for p in paths if p.name == "occ_part.igs"))
    md = generate.iges_solid(MPI.COMM_WORLD, part, h=0.2)
    mesh, ft = md.mesh, md.facet_tags
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # OCC's group entity (type 402)
        geo = CadGeometry.from_iges(part)
    snapper = Snapper(mesh, ft, geo)
    mesh, ft, *_ = snapper.refine(mesh)
    cm, info = snapper.curved_mesh(degree=3)
    assert info.reduced_nodes == 0 and info.min_jacobian_ratio > 0.2
    x = cm.geometry.x
    rim = 0
    for f in np.unique(ft.values):
        nodes = boundary_nodes(cm, ft.find(f))
        p = x[nodes]
        r = np.hypot(p[:, 0] - 0.5, p[:, 1] - 0.5)
        lo, hi = p.min(axis=0), p.max(axis=0)
        flat = np.flatnonzero(hi - lo < 1e-9)
        if len(flat):  # an axis-aligned plane
            assert np.abs(p[:, flat[0]] - p[0, flat[0]]).max() < 1e-13
            rim += np.count_nonzero(np.abs(r - 0.2) < 1e-12)
        else:  # the hole's wall
            assert np.abs(r - 0.2).max() < 1e-12
            assert p[:, 2].min() > -1e-13 and p[:, 2].max() < 1 + 1e-13
    assert rim > 0  # the top and bottom planes' nodes on the rim circles
