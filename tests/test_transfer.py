"""Solution transfer through the parent maps: exactness, curved meshes, errors, MPI.

The meshes are a coarse disk (8-gon) and ball whose new boundary vertices
Nagata snapping moves well outside their parent cells, so the transfer must
extend the parent's polynomial there.  Independent truth: DOLFINx's own
interpolation of the same polynomial on the refined mesh, and DOLFINx's
``Function.eval`` (its own pull-back) in the parent cells.
"""

import itertools
import os
import subprocess
import sys

import basix
import basix.ufl
import numpy as np
import pytest
from mpi4py import MPI
from scipy.spatial import cKDTree

import dolfinx.fem as fem
import generate

from nagata_snap import FittedGeometry, NagataGeometry, Snapper
from nagata_snap.cad import CadGeometry
from nagata_snap.cad.iges import write_iges
from nagata_snap.mesh.lineage import parent_cells
from nagata_snap.cad.nurbs import sphere as nurbs_sphere
from nagata_snap.transfer import pull_back, transfer

HERE = os.path.dirname(__file__)
COMM = MPI.COMM_WORLD


def coarse_snapper(comm, dim, surface=NagataGeometry, n=8):
    """Snapper on a coarse disk (``n``-gon) or ball: Nagata (or ``surface``) snapping moves new
    boundary vertices well outside their parent cells.  Returns ``(snapper, mesh, facet_tags, tag)``."""
    if dim == 2:
        md, tag = generate.unit_disk(comm, n=n), generate.DISK_BOUNDARY
    else:
        md, tag = generate.ball(comm, radius=1.0, h=0.6), generate.BALL_SPHERE
    mesh, ft = md.mesh, md.facet_tags
    return Snapper(mesh, ft, surface(mesh, ft, tags=[tag])), mesh, ft, tag


def exactness_error(snapper, mesh0, mesh1, key):
    """Max error (relative to the field's size) of a transferred polynomial of the space's
    degree against DOLFINx's interpolant on the refined mesh, and the transfer's info."""
    V0, deg = space(mesh0, key)
    V1, _ = space(mesh1, key)
    f = polynomial(mesh0.topology.dim, deg, tuple(V0.element.value_shape))
    u0, exact = fem.Function(V0), fem.Function(V1)
    u0.interpolate(f)
    exact.interpolate(f)
    w, info = snapper.transfer(u0, V1, return_info=True)
    return max_abs(w.x.array - exact.x.array) / max_abs(exact.x.array), info


DEGREES = (2, 3, 4)  # curved coordinate degrees


def _snapped(dim):
    """Snapper refined once; straight meshes and curved ones {degree: mesh} of both levels."""
    snapper, mesh0, ft0, _ = coarse_snapper(COMM, dim)
    curved0 = {k: snapper.curved_mesh(degree=k)[0] for k in DEGREES}
    mesh1, *_ = snapper.refine(mesh0)
    curved1 = {k: snapper.curved_mesh(degree=k)[0] for k in DEGREES}
    return snapper, mesh0, mesh1, curved0, curved1, ft0


@pytest.fixture(scope="module", params=[2, 3], ids=["2d", "3d"])
def level(request):
    return (request.param, *_snapped(request.param))


def polynomial(dim, degree, shape=()):
    """Every monomial of total degree ``degree`` (and a linear part), one variant per component."""
    exps = [e for e in itertools.product(range(degree + 1), repeat=dim) if sum(e) == degree]

    def p(x, k=0):
        s = 0.3 + 0.1 * k + x[0] - 0.5 * x[1]
        for j, e in enumerate(exps):
            term = (1.0 + j + k) / len(exps)
            for i, a in enumerate(e):
                term = term * x[i] ** a
            s = s + term
        return s

    size = int(np.prod(shape)) if len(shape) else 0
    if not size:
        return p
    return lambda x: np.stack([p(x, k) for k in range(size)])


SPACES = {
    "P1": (("Lagrange", 1), 1),
    "P2": (("Lagrange", 2), 2),
    "P3": (("Lagrange", 3), 3),
    "P2-vector": ("vector", 2),
    "DG1": (("DG", 1), 1),
    "P2-tensor": ("tensor", 2),
    "DG2-legendre": ("legendre", 2),
}


def space(mesh, key):
    spec, deg = SPACES[key]
    cell, d = mesh.basix_cell(), mesh.topology.dim
    if spec == "vector":
        spec = basix.ufl.element("Lagrange", cell, 2, shape=(d,))
    elif spec == "tensor":
        spec = basix.ufl.element("Lagrange", cell, 2, shape=(d, d))
    elif spec == "legendre":
        spec = basix.ufl.element("DG", cell, 2, lagrange_variant=basix.LagrangeVariant.legendre)
    return fem.functionspace(mesh, spec), deg


def max_abs(a):
    return COMM.allreduce(float(np.abs(a).max(initial=0.0)), op=MPI.MAX)


@pytest.mark.parametrize("key", list(SPACES))
def test_polynomial_of_the_space_degree_is_transferred_exactly(level, key):
    """Parent interpolant of a degree-p polynomial -> transfer = child interpolant (1e-12),
    though snapping put child points well outside their parents."""
    _, snapper, mesh0, mesh1, *_ = level
    err, info = exactness_error(snapper, mesh0, mesh1, key)
    assert err <= 1e-12
    assert info.outside > 0 and info.max_outside > 1e-2  # boundary points left their parents
    assert info.newton_points == 0  # straight parents: one affine inverse each


def _max_eval_mismatch(snapper, m0, m1):
    """Transfer a smooth P2 vector field from ``m0`` to ``m1``; return the largest difference
    of a dof from DOLFINx's ``Function.eval`` of the source at the dof's point in the parent
    of one of the cells holding it, and the transfer's info."""
    dim = m1.topology.dim
    el = ("Lagrange", 2, (dim,))
    V0, V1 = fem.functionspace(m0, el), fem.functionspace(m1, el)
    u0 = fem.Function(V0)
    u0.interpolate(lambda x: np.stack([np.sin(2 * x[0]) * np.exp(x[1]) + 2, np.cos(x[dim - 1])
                                       + x[0] ** 3, *([x[2] ** 4] if dim == 3 else [])]))
    w, info = snapper.transfer(u0, V1, return_info=True)
    n1 = m1.topology.index_map(dim).size_local
    dofs = V1.dofmap.list[:n1]
    cells = np.repeat(snapper.parent_cells, dofs.shape[1]).astype(np.int32)
    cand = u0.eval(V1.tabulate_dof_coordinates()[dofs.ravel()], cells).reshape(len(cells), -1)
    got = w.x.array.reshape(-1, dim)[dofs.ravel()]
    diff = np.full(V1.dofmap.index_map.size_local + V1.dofmap.index_map.num_ghosts, np.inf)
    np.minimum.at(diff, dofs.ravel(), np.abs(got - cand).max(axis=1))
    n_own = V1.dofmap.index_map.size_local
    return COMM.allreduce(float(diff[:n_own].max()), op=MPI.MAX), info


@pytest.mark.parametrize("combo", ["straight-straight", "curved2-curved2", "straight-curved2",
                                   "curved2-straight", "curved3-curved3", "curved4-curved4",
                                   "curved2-curved4"])
def test_value_is_the_parent_polynomial_at_the_child_point(level, combo):
    """A smooth non-polynomial field: every dof is u0 evaluated (by DOLFINx, in the parent
    cell of one of the children holding it) at the child's point, on straight meshes and
    curved ones of degree 2-4 (gll_warped nodes for 3 and 4)."""
    dim, snapper, mesh0, mesh1, curved0, curved1, _ = level
    a, b = combo.split("-")
    m0 = curved0[int(a[-1])] if a.startswith("curved") else mesh0
    m1 = curved1[int(b[-1])] if b.startswith("curved") else mesh1
    err, info = _max_eval_mismatch(snapper, m0, m1)
    assert err < 1e-12
    if combo.startswith("curved"):
        assert info.newton_points > 0 and 1 <= info.newton_iterations <= 8
    # linear fields are reproduced exactly by P2 on these (Nagata: quadratic) geometries
    el = ("Lagrange", 2, (dim,))
    V0, V1 = fem.functionspace(m0, el), fem.functionspace(m1, el)
    lin = lambda x: np.stack([1 + x[0] - 2 * x[1] + 0.5 * x[dim - 1]] * dim)  # noqa: E731
    u0, exact = fem.Function(V0), fem.Function(V1)
    u0.interpolate(lin)
    exact.interpolate(lin)
    assert max_abs(snapper.transfer(u0, V1).x.array - exact.x.array) < 1e-13


@pytest.mark.parametrize("dim", [2, 3])
def test_fitted_surface_levels(dim):
    """Between two levels snapped onto a ``FittedGeometry`` (degree-4 fits, no CAD): a P2 polynomial
    is transferred exactly on the straight meshes though the fitted surface put the new boundary
    vertices outside their parents; on ``curved_mesh(degree=3)`` of both levels (cells on the fitted
    surface, Newton pull-back) every dof of a smooth field is DOLFINx's evaluation of the source in
    the parent, and a linear field in P3 is reproduced."""
    # the disk a 16-gon: on the 8-gon the fits disagree and the guard keeps Nagata's curves
    snapper, mesh0, ft0, tag = coarse_snapper(COMM, dim, FittedGeometry, n=16)
    c0, _ = snapper.curved_mesh(degree=3)
    mesh1, *_ = snapper.refine(mesh0)
    c1, _ = snapper.curved_mesh(degree=3)
    # a surface other than Nagata's: the facets' centres lie elsewhere
    centre = np.full((snapper.geometry.num_patches, 1, dim), 1.0 / dim)
    nagata = NagataGeometry(mesh0, ft0, tags=[tag])
    assert np.abs(snapper.geometry.evaluate(np.arange(len(centre)), centre)
                  - nagata.evaluate(np.arange(len(centre)), centre)).max() > 1e-4
    err, info = exactness_error(snapper, mesh0, mesh1, "P2")
    assert err <= 1e-12
    assert info.outside > 0 and info.max_outside > 1e-2
    err, info = _max_eval_mismatch(snapper, c0, c1)
    assert err < 1e-12
    assert info.newton_points > 0 and 1 <= info.newton_iterations <= 8
    V0, V1 = fem.functionspace(c0, ("Lagrange", 3)), fem.functionspace(c1, ("Lagrange", 3))
    lin = lambda x: 1 + x[0] - 2 * x[1] + 0.5 * x[dim - 1]  # noqa: E731
    u0, exact = fem.Function(V0), fem.Function(V1)
    u0.interpolate(lin)
    exact.interpolate(lin)
    assert max_abs(snapper.transfer(u0, V1).x.array - exact.x.array) < 1e-12


def test_cubic_cad_geometry_points_outside_curved_parents(tmp_path):
    """Degree-3 meshes of a ball on the NURBS sphere (truly cubic cells): the child's nodes on
    the sphere lie outside the parent's cubic surface, Newton pulls them back there."""
    path = tmp_path / "sphere.igs"
    if COMM.rank == 0:
        write_iges(path, surfaces=[nurbs_sphere((0.0, 0.0, 0.0), 1.0)])
    COMM.barrier()
    md = generate.ball(COMM, radius=1.0, h=0.6)
    snapper = Snapper(md.mesh, md.facet_tags, CadGeometry.from_iges(path), tags=[generate.BALL_SPHERE])
    c0, _ = snapper.curved_mesh(degree=3)
    snapper.refine(md.mesh)
    c1, _ = snapper.curved_mesh(degree=3)
    err, info = _max_eval_mismatch(snapper, c0, c1)
    assert err < 1e-12
    assert info.outside > 0 and info.newton_points > 0 and info.newton_iterations <= 8


def _sup_error(u, f):
    """Max |u - f| over the P5 lattice points of every owned cell (DOLFINx eval)."""
    mesh = u.function_space.mesh
    tdim = mesh.topology.dim
    ct = basix.CellType.triangle if tdim == 2 else basix.CellType.tetrahedron
    X = basix.create_lattice(ct, 5, basix.LatticeType.equispaced, True)
    n = mesh.topology.index_map(tdim).size_local
    nodes = mesh.geometry.x[mesh.geometry.dofmaps[0][:n]]  # affine cells
    lam = np.column_stack([1 - X.sum(axis=1), X])
    pts = np.einsum("qv,cvd->cqd", lam, nodes[:, : tdim + 1]).reshape(-1, 3)
    cells = np.repeat(np.arange(n, dtype=np.int32), len(X))
    return max_abs(u.eval(pts, cells).ravel() - f(pts.T).T.ravel())


def test_smooth_field_error_is_the_parent_interpolants(level):
    """No dof is zero-filled: the transferred error at the child's dofs stays that of the parent
    interpolant (sampled densely on the parent); a point search zero-fills where it finds no cell."""
    dim, snapper, mesh0, mesh1, *_ = level
    el = ("Lagrange", 2, (dim,))
    V0, V1 = fem.functionspace(mesh0, el), fem.functionspace(mesh1, el)

    def f(x):  # >= 1 everywhere, so a zero-filled dof has error >= 1
        return np.stack([2 + np.sin(3 * x[0]) * np.cos(2 * x[1]) + 0.5 * x[dim - 1] ** 2] * dim)

    u0, exact = fem.Function(V0), fem.Function(V1)
    u0.interpolate(f)
    exact.interpolate(f)
    n_own = V1.dofmap.index_map.size_local * dim
    w = snapper.transfer(u0, V1)
    e_parent = _sup_error(u0, f)
    e_transfer = max_abs(w.x.array[:n_own] - exact.x.array[:n_own])
    assert COMM.allreduce(int(np.count_nonzero(np.abs(w.x.array) < 0.5))) == 0
    assert 0.1 * e_parent < e_transfer < 1.5 * e_parent
    cells = np.arange(mesh1.topology.index_map(dim).size_local, dtype=np.int32)
    nm = fem.Function(V1)
    nm.interpolate_nonmatching(u0, cells, fem.create_interpolation_data(V1, V0, cells, 1e-8))
    zeros = COMM.allreduce(int(np.count_nonzero(nm.x.array[:n_own] == 0.0)))
    if zeros:  # DOLFINx 0.11 zero-fills here in 3D (points outside every cell of the old mesh)
        assert max_abs(nm.x.array[:n_own] - exact.x.array[:n_own]) >= 1.0 > 10 * e_transfer


def test_mixed_sub_spaces_and_sub_functions(level):
    """Collapsed sub-spaces of Taylor-Hood, and an uncollapsed sub-function as the source."""
    dim, snapper, mesh0, mesh1, *_ = level
    cell = mesh0.basix_cell()
    me = basix.ufl.mixed_element([basix.ufl.element("Lagrange", cell, 2, shape=(dim,)),
                                  basix.ufl.element("Lagrange", cell, 1)])
    W0, W1 = fem.functionspace(mesh0, me), fem.functionspace(mesh1, me)
    fu, fp = polynomial(dim, 2, (dim,)), polynomial(dim, 1)
    w0 = fem.Function(W0)
    w0.sub(0).interpolate(fu)
    w0.sub(1).interpolate(fp)
    w0.x.scatter_forward()
    for i, f in ((0, fu), (1, fp)):
        Vi, _ = W1.sub(i).collapse()
        exact = fem.Function(Vi)
        exact.interpolate(f)
        for src in (w0.sub(i).collapse(), w0.sub(i)):
            out = snapper.transfer(src, Vi)
            assert max_abs(out.x.array - exact.x.array) <= 1e-12 * max_abs(exact.x.array)
    with pytest.raises(ValueError, match="sub-space of a mixed space: collapse it"):
        snapper.transfer(w0.sub(0).collapse(), W1.sub(0))
    with pytest.raises(ValueError, match="mixed or quadrature element"):
        snapper.transfer(w0, W1)


def test_two_levels_through_composed_maps():
    """transfer(u0, V2, P1[P2]): straight from level 0 to level 2 (polynomial exact)."""
    md = generate.unit_disk(COMM, n=8)
    mesh0, ft = md.mesh, md.facet_tags
    snapper = Snapper(mesh0, ft, NagataGeometry(mesh0, ft))
    mesh1, *_ = snapper.refine(mesh0)
    P1 = snapper.parent_cells
    mesh2, *_ = snapper.refine(mesh1)
    P2 = snapper.parent_cells
    assert P2.max() < mesh1.topology.index_map(2).size_local  # parents are owned cells
    V0, V2 = fem.functionspace(mesh0, ("Lagrange", 3)), fem.functionspace(mesh2, ("Lagrange", 3))
    f = polynomial(2, 3)
    u0, exact = fem.Function(V0), fem.Function(V2)
    u0.interpolate(f)
    exact.interpolate(f)
    assert max_abs(transfer(u0, V2, P1[P2]).x.array - exact.x.array) < 1e-12 * max_abs(exact.x.array)
    with pytest.raises(ValueError, match="must live on the mesh given to the last"):
        snapper.transfer(u0, V2)  # level 0 is not the last refine's parent


def test_plain_refine_with_the_lineage_parent_map():
    """Without a Snapper: dolfinx.mesh.refine + lineage.parent_cells (the 0.11 index quirk
    handled there) + transfer, adaptive refinement, vector P2 exact."""
    import dolfinx.mesh

    mesh0 = generate.unit_disk(COMM, n=12).mesh
    mesh0.topology.create_entities(1)
    edges = np.arange(0, mesh0.topology.index_map(1).size_local, 3, dtype=np.int32)
    mesh1, parent_cell, _ = dolfinx.mesh.refine(mesh0, edges)
    n0 = mesh0.topology.index_map(2).size_local
    P = parent_cells(mesh1, mesh0, parent_cell, np.ones(n0, dtype=bool))
    V0, V1 = (fem.functionspace(m, ("Lagrange", 2, (2,))) for m in (mesh0, mesh1))
    f = polynomial(2, 2, (2,))
    u0, exact = fem.Function(V0), fem.Function(V1)
    u0.interpolate(f)
    exact.interpolate(f)
    w, info = transfer(u0, V1, P, return_info=True)
    assert max_abs(w.x.array - exact.x.array) < 1e-12 * max_abs(exact.x.array)
    assert info.outside == 0  # nested levels: every point inside its parent


@pytest.mark.parametrize("family, name", [("N1curl", "N1E"), ("RT", "RT"), ("Bubble", "bubble")])
def test_unsupported_families_are_named(level, family, name):
    dim, snapper, mesh0, mesh1, *_ = level
    deg = 3 if family == "Bubble" and dim == 2 else (4 if family == "Bubble" else 1)
    u0 = fem.Function(fem.functionspace(mesh0, (family, deg)))
    with pytest.raises(ValueError, match=f"Lagrange.*{name} element: interpolate into a"):
        snapper.transfer(u0, fem.functionspace(mesh1, (family, deg)))
    with pytest.raises(ValueError, match=f"{name} element"):
        snapper.transfer(fem.Function(fem.functionspace(mesh0, ("Lagrange", 1))),
                         fem.functionspace(mesh1, (family, deg)))


def test_bad_input_errors(level):
    dim, snapper, mesh0, mesh1, *_ = level
    u0 = fem.Function(fem.functionspace(mesh0, ("Lagrange", 1)))
    V1 = fem.functionspace(mesh1, ("Lagrange", 1))
    with pytest.raises(ValueError, match="value shape"):
        snapper.transfer(u0, fem.functionspace(mesh1, ("Lagrange", 1, (dim,))))
    with pytest.raises(ValueError, match="must live on the mesh returned by"):
        snapper.transfer(u0, fem.functionspace(mesh0, ("Lagrange", 1)))
    with pytest.raises(ValueError, match="u must live on the mesh given to"):
        snapper.transfer(fem.Function(V1), V1)
    with pytest.raises(ValueError, match="parent_cells must map the"):
        transfer(u0, V1, snapper.parent_cells[:-1])
    ft0 = level[-1]
    fresh = Snapper(mesh0, ft0, snapper.geometry)
    with pytest.raises(ValueError, match=r"call Snapper\.refine first"):
        fresh.transfer(u0, V1)


def test_pull_back_newton_against_a_known_quadratic_map():
    """Newton pull-back through a curved P2 triangle inverts its map, also outside the cell."""
    e = basix.create_element(basix.ElementFamily.P, basix.CellType.triangle, 2,
                             basix.LagrangeVariant.gll_warped)
    nodes = e.points + np.array([[0, 0], [0, 0], [0, 0], [0.1, 0.05], [-0.08, 0.0], [0.0, -0.12]])
    X = np.array([[0.2, 0.3], [0.5, 0.5], [0.6, -0.05], [-0.04, 0.5], [0.55, 0.48]])
    y = e.tabulate(0, X)[0, :, :, 0] @ nodes
    n = len(X)
    Xb, its = pull_back(np.repeat(nodes[None], n, axis=0), y, e, np.full((n, 2), 1 / 3))
    assert np.abs(Xb - X).max() < 1e-13 and its <= 8
    # a tiny cell far from the origin: Newton ends at round-off (steps stop halving)
    far, scale = np.array([300.0, -200.0]), 1e-5
    Xf, _ = pull_back(np.repeat(far + scale * nodes[None], n, axis=0), far + scale * y, e,
                      np.full((n, 2), 1 / 3))
    assert np.abs(Xf - X).max() < 1e-6
    with pytest.raises(RuntimeError, match="did not converge"):
        pull_back(np.repeat(nodes[None], 1, axis=0), np.array([[1e3, -1e3]]), e,
                  np.full((1, 2), 1 / 3), max_iterations=2)


@pytest.mark.mpi
@pytest.mark.parametrize("dim", [2, 3])
def test_mpi_matches_serial(dim, tmp_path):
    """Serial = mpiexec -n 2 = -n 3 to 1e-12, owned and ghost dofs, over two levels (the
    second with a ghosted parent).  2D: every dof value at the same coordinates.  3D:
    DOLFINx's tetrahedron refinement picks interior diagonals by a partition-dependent
    tie-break, so only the exactness and the level-1 boundary dofs (same gmsh parent, same
    snapped coordinates) are comparable."""
    mpiexec = os.path.join(os.path.dirname(sys.executable), "mpiexec")
    res = {}
    for n in (1, 2, 3):
        out = tmp_path / f"np{n}.npz"
        cmd = [mpiexec, "-n", str(n), sys.executable, os.path.join(HERE, "mpi", "transfer_mpi.py"),
               str(dim), str(out)]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stdout + r.stderr
        res[n] = np.load(out)
    for n in (1, 2, 3):
        for key in res[n].files:
            if key.startswith("exact_err"):
                assert res[n][key] < 1e-12, (n, key)
        if n > 1:  # the refined meshes have ghost cells on every process
            assert np.all(res[n]["ghost_cells_1"] > 0) and np.all(res[n]["ghost_cells_2"] > 0)
    keys = ["dofs_all_1", "dofs_all_2"] if dim == 2 else ["dofs_boundary_1"]
    for n in (2, 3):
        for key in keys + (["dofs_ghost_1", "dofs_ghost_2"] if dim == 2 else []):
            a, b = res[1][key.replace("ghost", "all")], res[n][key]  # rows: x, y, z, values
            if "ghost" not in key:
                assert a.shape == b.shape, key
            assert len(b) > 0, key
            d, i = cKDTree(a[:, :3]).query(b[:, :3])
            assert d.max() <= 1e-12, key
            if "ghost" not in key:
                assert len(np.unique(i)) == len(a), key
            assert np.abs(a[i, 3:] - b[:, 3:]).max() < 1e-12, key
