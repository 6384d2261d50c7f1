"""DFG 2D-1 steady Navier-Stokes benchmark: solver, forces, indicator, marking.

Problem (Schaefer & Turek 1996; reference values of John & Matthies 2001):
channel [0, 2.2] x [0, 0.41] m minus the cylinder of radius 0.05 m centred at
(0.2, 0.2); kinematic viscosity nu = 1e-3 m^2/s, density rho = 1 kg/m^3;
parabolic inflow u = (4 U_max y (H - y) / H^2, 0) with U_max = 0.3 m/s,
H = 0.41 m; no slip on the walls and the cylinder; "do-nothing" outflow
nu du/dn - p n = 0 at x = 2.2.  Pressure is kinematic (p / rho, m^2/s^2), and
with rho = 1 the forces are in N/m (per unit depth).

Discretisation: Taylor-Hood P2/P1 (``degree=(2, 1)``) on one mixed space,
steady Navier-Stokes residual

    R(u, p; v, q) = (nu grad u, grad v) + ((grad u) u, v) - (p, div v)
                    - (q, div u),

Newton's method (PETSc SNES ``newtonls``) with a direct MUMPS LU at every
step, starting from zero: at u = 0 the Newton Jacobian is the Stokes
operator, so the first step is a Stokes solve.  The do-nothing condition is
natural for this form, so the pressure needs no normalisation.

Forces on the cylinder, F = integral over S of (-sigma n) with n the unit
normal pointing out of the fluid and sigma = nu grad u - p I:

* volume (residual) form: F_i = -R(u_h, p_h; w_i, 0) where w_i is the P2
  function equal to e_i at the velocity DOFs on the cylinder and 0 at all
  other DOFs.  For smooth problems its error behaves like the square of the
  energy-norm error, much faster than the surface form; it is the
  recommended value (on a polygonal cylinder both are limited by the
  geometry error, about 1.25e-2 * (16 / n)^2 for an inscribed n-gon);
* surface form: F = -int_S (nu grad u_h n - p_h n) ds, for comparison.

Coefficients c = 2 F / (rho U_mean^2 D), U_mean = 2 U_max / 3 = 0.2 m/s,
D = 0.1 m.  Pressure difference dp = p(0.15, 0.2) - p(0.25, 0.2) by point
evaluation (works in parallel).

Typical use::

    import mpi4py.MPI as MPI
    from meshes.generate import dfg_channel
    from demos.dfg import solve_dfg, ns_residual_indicator, dorfler_mark
    data = dfg_channel(MPI.COMM_WORLD, n_circle=16)
    res = solve_dfg(data.mesh, data.facet_tags)
    eta = ns_residual_indicator(res.u, res.p, data.facet_tags)
    edges = dorfler_mark(data.mesh, eta, theta=0.5)
    mesh1, parent_cell, parent_facet = dolfinx.mesh.refine(
        data.mesh, edges, partitioner=None,
        option=dolfinx.mesh.RefinementOption.parent_cell_and_facet)
    mesh1.topology.create_entities(1)
    tags1 = dolfinx.mesh.transfer_meshtag(data.facet_tags, mesh1, parent_cell, parent_facet)
    res1 = solve_dfg(mesh1, tags1, initial_guess=res.u)

(``partitioner=None`` keeps the refined mesh unghosted: in DOLFINx 0.11
``transfer_meshtag`` rejects ghosted meshes, and after a refine with the
default placeholder partitioner, which adds ghost cells, it corrupts memory
in parallel.)
"""

from __future__ import annotations

import dataclasses
import itertools
import time
import typing

import mpi4py.MPI as MPI  # must precede dolfinx/petsc4py

import basix.ufl
import numpy as np
import numpy.typing as npt
import ufl

import dolfinx
import dolfinx.fem.petsc
from dolfinx import fem, geometry
from dolfinx import mesh as dmesh

# --------------------------------------------------------------------------
# Problem data
# --------------------------------------------------------------------------
#: Facet tags (same values as ``meshes.generate``)
INLET = 1
OUTLET = 2
WALLS = 3
CYLINDER = 4

NU = 1.0e-3  #: kinematic viscosity [m^2/s]
RHO = 1.0  #: density [kg/m^3]
U_MAX = 0.3  #: peak inflow velocity [m/s]
H = 0.41  #: channel height [m]
D = 0.1  #: cylinder diameter [m]
U_MEAN = 2.0 * U_MAX / 3.0  #: mean inflow velocity [m/s]
P_FRONT = (0.15, 0.2)  #: front point of the cylinder [m]
P_BACK = (0.25, 0.2)  #: rear point of the cylinder [m]

#: Reference values (seeds/README.md; John & Matthies 2001)
C_D_REF = 5.57953523384
C_L_REF = 0.010618948146
DP_REF = 0.11752016697

DEFAULT_PETSC_OPTIONS: dict[str, typing.Any] = {
    "snes_type": "newtonls",
    "snes_linesearch_type": "none",
    "snes_rtol": 1.0e-11,
    "snes_atol": 1.0e-11,
    "snes_stol": 0.0,
    "snes_max_it": 25,
    "snes_error_if_not_converged": True,
    "ksp_type": "preonly",
    "pc_type": "lu",
    "pc_factor_mat_solver_type": "mumps",
    "ksp_error_if_not_converged": True,
}

_prefix_counter = itertools.count()


@dataclasses.dataclass
class DFGResult:
    """Result of :func:`solve_dfg`.

    Attributes:
        dofs: global number of degrees of freedom (velocity + pressure).
        num_cells: global number of cells.
        c_D, c_L: drag and lift coefficients from the volume (residual) form.
        dp: pressure difference p(0.15, 0.2) - p(0.25, 0.2) [m^2/s^2].
        c_D_surface, c_L_surface: coefficients from the surface traction
            integral over the facets tagged CYLINDER.
        err_c_D, err_c_L, err_dp, err_c_D_surface, err_c_L_surface:
            relative errors |value - ref| / |ref| against C_D_REF, C_L_REF,
            DP_REF.
        solve_time: wall time of the Newton solve [s] (assembly + LU).
        total_time: wall time of the whole call [s] (setup, JIT, solve,
            post-processing).
        newton_iterations: number of Newton steps taken.
        residual_norms: SNES residual 2-norm history (initial + each step).
        dp_extrapolated: True if a pressure point was not inside any cell
            (it lies outside the discrete domain) and was evaluated in the
            nearest cell instead.
        u, p: velocity (P2 vector) and pressure (P1) Functions (collapsed).
    """

    dofs: int
    num_cells: int
    c_D: float
    c_L: float
    dp: float
    c_D_surface: float
    c_L_surface: float
    err_c_D: float
    err_c_L: float
    err_dp: float
    err_c_D_surface: float
    err_c_L_surface: float
    solve_time: float
    total_time: float
    newton_iterations: int
    residual_norms: list[float] = dataclasses.field(default_factory=list, repr=False)
    dp_extrapolated: bool = False
    u: fem.Function | None = dataclasses.field(default=None, repr=False)
    p: fem.Function | None = dataclasses.field(default=None, repr=False)

    def row(self) -> dict[str, float | int]:
        """The scalar fields as a flat dict (for tables/CSV)."""
        return {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if f.name not in ("u", "p", "residual_norms")
        }


def _rel(value: float, ref: float) -> float:
    return abs(value - ref) / abs(ref)


def inflow_profile(x: npt.NDArray[np.floating], u_max: float = U_MAX) -> np.ndarray:
    """Parabolic DFG inflow velocity [m/s] at points ``x`` (shape (3, n))."""
    ux = 4.0 * u_max * x[1] * (H - x[1]) / H**2
    return np.vstack((ux, np.zeros_like(ux)))


def ns_residual_form(u, p, v, q=None, nu: float | fem.Constant = NU, dx=None):
    """UFL residual R(u, p; v, q) of the steady NS equations (f = 0).

    R = (nu grad u, grad v) + ((grad u) u, v) - (p, div v) [- (q, div u)].
    Boundary terms vanish by the do-nothing condition (outlet) or because
    the test function vanishes on Dirichlet boundaries.
    """
    dx = ufl.dx if dx is None else dx
    F = (
        nu * ufl.inner(ufl.grad(u), ufl.grad(v)) * dx
        + ufl.inner(ufl.grad(u) * u, v) * dx
        - p * ufl.div(v) * dx
    )
    if q is not None:
        F -= q * ufl.div(u) * dx
    return F


def _boundary_indicator(V: fem.FunctionSpace, facets: np.ndarray, component: int) -> fem.Function:
    """P2 vector Function: e_component at the DOFs on ``facets``, 0 elsewhere."""
    fdim = V.mesh.topology.dim - 1
    w = fem.Function(V)
    dofs = fem.locate_dofs_topological(V, fdim, facets)  # blocked, incl. remote
    bs = V.dofmap.index_map_bs
    w.x.array[bs * dofs + component] = 1.0
    w.x.scatter_forward()
    return w


def _point_values(f: fem.Function, points: npt.NDArray[np.floating]) -> tuple[np.ndarray, bool]:
    """Evaluate scalar ``f`` at ``points`` (shape (n, 3)) on every rank.

    Each rank looks for the points in its owned cells; the value of the
    lowest rank that found a point is broadcast.  A point found nowhere
    (outside the discrete domain, e.g. on a curved boundary approximated
    from inside) is evaluated in the globally nearest cell (polynomial
    extrapolation) and the returned flag is True.
    """
    msh = f.function_space.mesh
    comm = msh.comm
    tdim = msh.topology.dim
    n_owned = msh.topology.index_map(tdim).size_local
    owned = np.arange(n_owned, dtype=np.int32)
    pts = np.ascontiguousarray(points, dtype=msh.geometry.x.dtype)
    tree = geometry.bb_tree(msh, tdim, entities=owned)
    cand = geometry.compute_collisions_points(tree, pts)
    coll = geometry.compute_colliding_cells(msh, cand, pts)
    npts = pts.shape[0]
    local = np.full(npts, np.nan)
    for i in range(npts):  # a handful of points
        cells = coll.links(i)
        if len(cells) > 0:
            local[i] = f.eval(pts[i], cells[:1])[0]
    gathered = np.array(comm.allgather(local))  # (size, npts)
    values = np.full(npts, np.nan)
    missing = []
    for i in range(npts):
        hit = np.flatnonzero(~np.isnan(gathered[:, i]))
        if hit.size:
            values[i] = gathered[hit[0], i]
        else:
            missing.append(i)
    if missing:
        mid_tree = geometry.create_midpoint_tree(msh, tdim, owned)
        mpts = pts[missing]
        if n_owned > 0:
            cells = geometry.compute_closest_entity(tree, mid_tree, msh, mpts)
            dist = np.sqrt(geometry.squared_distance(msh, tdim, cells, mpts))
        else:
            cells = np.full(len(missing), -1, dtype=np.int32)
            dist = np.full(len(missing), np.inf)
        all_dist = np.array(comm.allgather(dist))
        best = np.argmin(all_dist, axis=0)
        local_vals = np.full(len(missing), np.nan)
        for j in range(len(missing)):
            if best[j] == comm.rank and cells[j] >= 0:
                local_vals[j] = f.eval(mpts[j], cells[j : j + 1])[0]
        vals = np.array(comm.allgather(local_vals))
        for j, i in enumerate(missing):
            values[i] = vals[best[j], j]
    return values, bool(missing)


def solve_dfg(
    mesh: dmesh.Mesh,
    facet_tags: dmesh.MeshTags,
    *,
    degree: tuple[int, int] = (2, 1),
    petsc_options: dict[str, typing.Any] | None = None,
    nu: float = NU,
    u_max: float = U_MAX,
    tags: dict[str, int] | None = None,
    initial_guess: fem.Function | None = None,
) -> DFGResult:
    """Solve steady DFG 2D-1 Navier-Stokes on ``mesh`` and evaluate the benchmark.

    Args:
        mesh: triangular mesh of the channel with the cylinder cut out
            (coordinates in m).
        facet_tags: facet MeshTags with INLET=1, OUTLET=2, WALLS=3,
            CYLINDER=4 (override with ``tags``).
        degree: (velocity degree, pressure degree); Taylor-Hood (2, 1) by
            default.
        petsc_options: SNES/KSP options merged over
            :data:`DEFAULT_PETSC_OPTIONS` (Newton, no line search, MUMPS LU,
            rtol = atol = 1e-11).
        nu: kinematic viscosity [m^2/s].
        u_max: peak inflow velocity [m/s].  The coefficients are normalised
            with U_mean = 2 u_max / 3, so the reference errors only make
            sense for the defaults.
        tags: optional mapping with keys "inlet", "outlet", "walls",
            "cylinder" to facet tag values.
        initial_guess: optional velocity Function used as the Newton
            initial guess, on ``mesh`` or on another mesh (e.g. the previous
            adaptive level: non-matching interpolation; points outside that
            mesh get zero).  Default zero, whose first Newton step is the
            Stokes solve.

    Returns:
        DFGResult (c_D, c_L volume form; surface-form coefficients; dp;
        relative errors; timings; solution Functions).
    """
    t_start = time.perf_counter()
    comm = mesh.comm
    tg = {"inlet": INLET, "outlet": OUTLET, "walls": WALLS, "cylinder": CYLINDER}
    if tags:
        tg.update(tags)
    tdim = mesh.topology.dim
    fdim = tdim - 1
    gdim = mesh.geometry.dim
    mesh.topology.create_connectivity(fdim, tdim)

    ku, kp = degree
    cell = mesh.basix_cell()
    el_u = basix.ufl.element("Lagrange", cell, ku, shape=(gdim,))
    el_p = basix.ufl.element("Lagrange", cell, kp)
    W = fem.functionspace(mesh, basix.ufl.mixed_element([el_u, el_p]))
    V, V_to_W = W.sub(0).collapse()

    # Dirichlet conditions
    u_in = fem.Function(V)
    u_in.interpolate(lambda x: inflow_profile(x, u_max))
    u_zero = fem.Function(V)
    bcs = []
    for key, g in (("inlet", u_in), ("walls", u_zero), ("cylinder", u_zero)):
        facets = facet_tags.find(tg[key])
        dofs = fem.locate_dofs_topological((W.sub(0), V), fdim, facets)
        bcs.append(fem.dirichletbc(g, dofs, W.sub(0)))

    # Nonlinear problem
    w = fem.Function(W)
    if initial_guess is not None:
        u0 = fem.Function(V)
        if initial_guess.function_space.mesh is mesh:
            u0.interpolate(initial_guess)
        else:  # e.g. the solution on the parent mesh before refinement
            n_cells = mesh.topology.index_map(tdim).size_local
            cells = np.arange(n_cells, dtype=np.int32)
            idata = fem.create_interpolation_data(V, initial_guess.function_space, cells, 1e-8)
            u0.interpolate_nonmatching(initial_guess, cells, idata)
        u0.x.scatter_forward()
        w.x.array[V_to_W] = u0.x.array
        w.x.scatter_forward()
    u, p = ufl.split(w)
    v, q = ufl.TestFunctions(W)
    nu_c = fem.Constant(mesh, dolfinx.default_scalar_type(nu))
    F = ns_residual_form(u, p, v, q, nu_c)
    opts = dict(DEFAULT_PETSC_OPTIONS)
    if petsc_options:
        opts.update(petsc_options)
    prefix = f"dfg{next(_prefix_counter)}_"
    problem = dolfinx.fem.petsc.NonlinearProblem(
        F, w, bcs=bcs, petsc_options_prefix=prefix, petsc_options=opts
    )
    snes = problem.solver
    snes.setConvergenceHistory()
    t0 = time.perf_counter()
    problem.solve()
    solve_time = time.perf_counter() - t0
    reason = snes.getConvergedReason()
    if reason <= 0:
        raise RuntimeError(f"Newton did not converge (SNES reason {reason})")
    its = int(snes.getIterationNumber())
    hist = [float(r) for r in snes.getConvergenceHistory()[0]]
    w.x.scatter_forward()

    # Forces: volume (residual) form
    cyl_facets = facet_tags.find(tg["cylinder"])
    scale = 2.0 / (RHO * U_MEAN**2 * D)
    forces = []
    for comp in range(gdim):
        wi = _boundary_indicator(V, cyl_facets, comp)
        Ri = fem.form(ns_residual_form(u, p, wi, None, nu_c))
        forces.append(-comm.allreduce(fem.assemble_scalar(Ri), op=MPI.SUM))
    # Forces: surface traction
    n = ufl.FacetNormal(mesh)
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=facet_tags)
    traction = nu_c * ufl.grad(u) * n - p * n
    forces_s = []
    for comp in range(gdim):
        Fi = fem.form(-traction[comp] * ds(tg["cylinder"]))
        forces_s.append(comm.allreduce(fem.assemble_scalar(Fi), op=MPI.SUM))
    c_D, c_L = scale * forces[0], scale * forces[1]
    c_Ds, c_Ls = scale * forces_s[0], scale * forces_s[1]

    # Pressure difference
    u_h = w.sub(0).collapse()
    p_h = w.sub(1).collapse()
    u_h.name, p_h.name = "u", "p"
    pts = np.array([[*P_FRONT, 0.0], [*P_BACK, 0.0]])
    pv, extrapolated = _point_values(p_h, pts)
    dp = float(pv[0] - pv[1])

    dofs = W.dofmap.index_map.size_global * W.dofmap.index_map_bs
    ncells = mesh.topology.index_map(tdim).size_global
    del problem
    return DFGResult(
        dofs=int(dofs),
        num_cells=int(ncells),
        c_D=float(c_D),
        c_L=float(c_L),
        dp=dp,
        c_D_surface=float(c_Ds),
        c_L_surface=float(c_Ls),
        err_c_D=_rel(c_D, C_D_REF),
        err_c_L=_rel(c_L, C_L_REF),
        err_dp=_rel(dp, DP_REF),
        err_c_D_surface=_rel(c_Ds, C_D_REF),
        err_c_L_surface=_rel(c_Ls, C_L_REF),
        solve_time=solve_time,
        total_time=time.perf_counter() - t_start,
        newton_iterations=its,
        residual_norms=hist,
        dp_extrapolated=extrapolated,
        u=u_h,
        p=p_h,
    )


# --------------------------------------------------------------------------
# Error indicator and marking
# --------------------------------------------------------------------------
def _scalar_basix_element(V: fem.FunctionSpace):
    """The scalar basix element of a (possibly blocked) Lagrange space."""
    e = V.ufl_element()
    if getattr(e, "block_size", 1) > 1:
        e = e.sub_elements[0]
    return e.basix_element


def traction_jump_terms(
    u: fem.Function,
    p: fem.Function,
    facet_tags: dmesh.MeshTags | None = None,
    *,
    nu: float = NU,
    outlet: int = OUTLET,
) -> npt.NDArray[np.float64]:
    """Facet part of the residual indicator, per owned cell.

    Returns, for every owned cell K,

        sum_{F in dK interior} 1/2 h_F ||[[sigma_h n]]||_F^2
      + sum_{F in dK, F tagged outlet} h_F ||sigma_h n||_F^2,

    sigma_h = nu grad u_h - p_h I, [[sigma_h n]] = sigma^+ n^+ + sigma^- n^-,
    h_F the facet diameter.  For P2/P1 on affine simplices sigma_h n is
    linear on each facet, so it is evaluated exactly from its values at the
    facet vertices: every owned cell computes its one-sided traction there
    (vectorised over cells), the two sides are summed in a facet-indexed
    vector with a reverse scatter (so it works on meshes with or without
    ghost cells and gives the serial result in parallel), and
    ||J||_F^2 = |F| k!/(k+2)! (sum_i |J_i|^2 + |sum_i J_i|^2) for a
    k-simplex facet with vertex values J_i.  Other exterior facets
    (Dirichlet) contribute nothing.
    """
    V = u.function_space
    Q = p.function_space
    msh = V.mesh
    tdim = msh.topology.dim
    gdim = msh.geometry.dim
    fdim = tdim - 1
    eu = _scalar_basix_element(V)
    ep = _scalar_basix_element(Q)
    if eu.degree > 2 or ep.degree > 1 or gdim != tdim:
        raise NotImplementedError("traction jumps need P<=2 velocity, P<=1 pressure, gdim == tdim")
    celltype = eu.cell_type
    nv = tdim + 1
    if msh.geometry.dofmaps[0].shape[1] != nv:
        raise NotImplementedError("affine simplex meshes only")
    for d0, d1 in ((tdim, fdim), (tdim, 0), (fdim, tdim)):
        msh.topology.create_connectivity(d0, d1)
    n_owned = msh.topology.index_map(tdim).size_local
    bs = V.dofmap.index_map_bs

    X = msh.geometry.x[msh.geometry.dofmaps[0][:n_owned], :gdim]  # (n, nv, gdim)
    Jt = X[:, 1:, :] - X[:, :1, :]  # rows x_k - x_0: J^T
    K = np.linalg.inv(np.transpose(Jt, (0, 2, 1)))  # (n, tdim, gdim)
    grad_lam = np.concatenate([-K.sum(axis=1, keepdims=True), K], axis=1)  # (n, nv, gdim)
    normals = -grad_lam / np.linalg.norm(grad_lam, axis=2, keepdims=True)  # facet k opp. vertex k

    ref = basix.geometry(celltype)  # reference vertices
    dphi = eu.tabulate(1, ref)[1:, :, :, 0]  # (tdim, nv, ndofs)
    U = u.x.array.reshape(-1, bs)[V.dofmap.list[:n_owned]]  # (n, ndofs, gdim)
    G = np.einsum("cai,dpa,cdj->cpij", U, dphi, K)  # grad u at the vertices
    phip = ep.tabulate(0, ref)[0, :, :, 0]  # (nv, ndofs_p)
    Pv = p.x.array[Q.dofmap.list[:n_owned]] @ phip.T  # (n, nv)
    sigma = nu * G - Pv[:, :, None, None] * np.eye(gdim)
    T = np.einsum("cvij,ckj->ckvi", sigma, normals)  # traction on facet k at vertex v

    fv = np.asarray(basix.topology(celltype)[fdim], dtype=np.int64)  # (nf, tdim)
    nf = fv.shape[0]
    c2v = msh.topology.connectivity(tdim, 0).array.reshape(-1, nv)[:n_owned]
    gids = msh.topology.index_map(0).local_to_global(c2v.ravel()).reshape(c2v.shape)[:, fv]
    locv = np.take_along_axis(
        np.broadcast_to(fv, gids.shape), np.argsort(gids, axis=2), axis=2
    )  # local vertices of each facet, sorted by global vertex index
    ci = np.arange(n_owned)[:, None, None]
    ki = np.arange(nf)[None, :, None]
    Tf = T[ci, ki, locv]  # (n, nf, tdim, gdim)
    c2f = msh.topology.connectivity(tdim, fdim).array.reshape(-1, nf)[:n_owned]

    width = tdim * gdim
    vec = dolfinx.la.vector(msh.topology.index_map(fdim), bs=width)
    arr = vec.array.reshape(-1, width)
    arr[:] = 0.0
    np.add.at(arr, c2f.ravel(), Tf.reshape(-1, width))
    vec.scatter_reverse(dolfinx.la.InsertMode.add)
    vec.scatter_forward()
    Jv = vec.array.reshape(-1, tdim, gdim)[c2f]  # (n, nf, tdim, gdim) jump at facet vertices

    # facet measure and diameter from the cell's own coordinates
    XF = X[:, fv, :]  # (n, nf, tdim, gdim)
    if fdim == 1:
        meas = np.linalg.norm(XF[:, :, 1] - XF[:, :, 0], axis=2)
        diam = meas
        coef = 1.0 / 6.0
    else:
        e1 = XF[:, :, 1] - XF[:, :, 0]
        e2 = XF[:, :, 2] - XF[:, :, 0]
        meas = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=2)
        diam = np.max(
            [np.linalg.norm(XF[:, :, a] - XF[:, :, b], axis=2) for a, b in ((0, 1), (0, 2), (1, 2))],
            axis=0,
        )
        coef = 1.0 / 12.0
    jnorm2 = meas * coef * (np.sum(Jv**2, axis=(2, 3)) + np.sum(Jv.sum(axis=2) ** 2, axis=2))

    nfac = msh.topology.index_map(fdim).size_local + msh.topology.index_map(fdim).num_ghosts
    weight = np.full(nfac, 0.5)
    weight[dmesh.exterior_facet_indices(msh.topology)] = 0.0
    if facet_tags is not None:
        weight[facet_tags.find(outlet)] = 1.0
    return np.sum(weight[c2f] * diam * jnorm2, axis=1)


def ns_residual_indicator(
    u: fem.Function,
    p: fem.Function,
    facet_tags: dmesh.MeshTags | None = None,
    *,
    nu: float = NU,
    outlet: int = OUTLET,
) -> fem.Function:
    """Cellwise residual error indicator eta_K for the steady NS solution.

    eta_K^2 = h_K^2 ||nu Lap u + f - (grad u) u - grad p||_K^2     (f = 0)
            + ||div u||_K^2
            + sum_{F in dK interior} 1/2 h_F ||[[nu grad u n - p n]]||_F^2
            + sum_{F in dK on outlet} h_F ||nu grad u n - p n||_F^2,

    with h_K the cell diameter (circumdiameter, ``ufl.CellDiameter``) and
    h_F the facet diameter.  The cell terms are assembled at once against
    DG0 test functions; the facet terms come from
    :func:`traction_jump_terms` (vectorised numpy, exact for P2/P1, and
    independent of the mesh's ghost mode).  Dirichlet facets carry no term.
    This is the standard residual estimator for the energy-norm error
    without its constants: a heuristic for marking, not a guaranteed bound.
    It is partition independent (parallel = serial up to round-off).

    Args:
        u: velocity Function (P2 vector), [m/s].
        p: pressure Function (P1), [m^2/s^2].
        facet_tags: facet tags; if given, the do-nothing residual on facets
            tagged ``outlet`` is included.
        nu: kinematic viscosity [m^2/s].
        outlet: tag of the outflow facets.

    Returns:
        DG0 Function with eta_K (not squared) on every local cell, ghosts
        updated.
    """
    msh = u.function_space.mesh
    Q0 = fem.functionspace(msh, ("DG", 0))
    phi = ufl.TestFunction(Q0)
    h = ufl.CellDiameter(msh)
    nu_c = fem.Constant(msh, dolfinx.default_scalar_type(nu))
    R = -nu_c * ufl.div(ufl.grad(u)) + ufl.grad(u) * u + ufl.grad(p)
    cell_form = fem.form(
        h**2 * ufl.inner(R, R) * phi * ufl.dx + ufl.div(u) ** 2 * phi * ufl.dx
    )
    vec = fem.assemble_vector(cell_form)  # cell integrals only: no scatter needed
    n_owned = Q0.dofmap.index_map.size_local
    eta2 = vec.array[:n_owned] + traction_jump_terms(u, p, facet_tags, nu=nu, outlet=outlet)
    eta = fem.Function(Q0, name="eta")
    eta.x.array[:n_owned] = np.sqrt(np.maximum(eta2, 0.0))
    eta.x.scatter_forward()
    return eta


def dorfler_cells(
    mesh: dmesh.Mesh, indicator: fem.Function | npt.ArrayLike, theta: float
) -> npt.NDArray[np.int32]:
    """Doerfler (bulk) marking: local indices of the owned cells to refine.

    Marks the smallest set of cells M, chosen by decreasing eta_K, with
    sum_{K in M} eta_K^2 >= theta * sum_K eta_K^2 (over all ranks).  All
    cells tied with the threshold value are marked, so the result does not
    depend on the partition: the owned indicator values are gathered on
    every rank and the same global threshold is computed everywhere.

    Args:
        mesh: the mesh the indicator lives on.
        indicator: DG0 Function (one value per cell) or array of eta_K for
            the owned cells (length ``index_map(tdim).size_local``).
        theta: bulk parameter in (0, 1]; theta = 1 marks every cell with
            eta_K > 0.
    """
    if not 0.0 < theta <= 1.0:
        raise ValueError("theta must be in (0, 1]")
    tdim = mesh.topology.dim
    n_owned = mesh.topology.index_map(tdim).size_local
    if isinstance(indicator, fem.Function):
        eta = np.asarray(indicator.x.array[:n_owned], dtype=float)
    else:
        eta = np.asarray(indicator, dtype=float)[:n_owned]
    eta2 = eta**2
    all_eta2 = np.concatenate(mesh.comm.allgather(eta2))
    order = np.sort(all_eta2)[::-1]
    csum = np.cumsum(order)
    total = csum[-1] if csum.size else 0.0
    if total <= 0.0:
        return np.zeros(0, dtype=np.int32)
    k = int(np.searchsorted(csum, theta * total * (1.0 - 1e-14)))
    k = min(k, order.size - 1)
    threshold = order[k]
    return np.flatnonzero(eta2 >= threshold).astype(np.int32)


def dorfler_mark(
    mesh: dmesh.Mesh, indicator: fem.Function | npt.ArrayLike, theta: float
) -> npt.NDArray[np.int32]:
    """Doerfler marking, returning the edges to pass to ``dolfinx.mesh.refine``.

    The marked cells (see :func:`dorfler_cells`) are converted to their
    incident edges (local edge indices) with
    ``dolfinx.mesh.compute_incident_entities(topology, cells, tdim, 1)``.
    """
    cells = dorfler_cells(mesh, indicator, theta)
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim, 1)
    return dmesh.compute_incident_entities(mesh.topology, cells, tdim, 1)


def print_table(results: typing.Sequence[DFGResult], comm=None) -> None:
    """Print dofs, coefficients and relative errors (rank 0 only)."""
    comm = MPI.COMM_WORLD if comm is None else comm
    if comm.rank != 0:
        return
    print(
        f"{'dofs':>8} {'c_D':>12} {'c_L':>12} {'dp':>12} {'err c_D':>9} {'err c_L':>9} "
        f"{'err dp':>9} {'errc_Dsurf':>10} {'errc_Lsurf':>10} {'newton':>6} {'t[s]':>7}"
    )
    for r in results:
        print(
            f"{r.dofs:8d} {r.c_D:12.8f} {r.c_L:12.8f} {r.dp:12.8f} {r.err_c_D:9.2e} "
            f"{r.err_c_L:9.2e} {r.err_dp:9.2e} {r.err_c_D_surface:10.2e} "
            f"{r.err_c_L_surface:10.2e} {r.newton_iterations:6d} {r.solve_time:7.2f}"
        )


if __name__ == "__main__":
    import os
    import sys

    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from meshes.generate import dfg_channel

    data = dfg_channel(MPI.COMM_WORLD, n_circle=16)
    res = solve_dfg(data.mesh, data.facet_tags)
    print_table([res])
