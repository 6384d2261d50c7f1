"""Interior smoothing after boundary snapping: the band problem and its two smoothers.

After ``dolfinx.mesh.refine`` the snapper moves new boundary nodes onto the
true geometry. The interior must then follow, otherwise the first layer of
cells can be crushed or inverted (Kadir 2010, section 3.4.1: smooth the
interior, then check every cell and reject the mesh if one inverted).

Two smoothers, both acting on the *displacement* ``d = x - x_ref`` relative
to the straight refined mesh ``x_ref`` (so the straight mesh is a fixed
point), both restricted to a *band* of cells around the moved nodes:

``'elastic'`` (default)
    Vector P1 finite element extension of the boundary displacement on the
    reference (straight) configuration, solved with PETSc:
    ``-div(E(K) sigma(d)) = 0`` (linear elasticity, or the vector Laplacian
    with ``model='harmonic'``), with Dirichlet data ``d`` on all constrained
    nodes. The stiffness ``E(K) = (V_max / |K|)^p`` (``|K|`` the reference
    cell measure, ``V_max`` the largest one in the band, ``p`` =
    ``exponent``) makes small cells nearly rigid, so they are translated
    rather than squashed (Jacobian-based stiffening). The element
    matrices are written out from the hat-function gradients (a test checks
    the result against the same form in UFL, assembled by DOLFINx).

``'laplace'``
    Jacobi sweeps of graph-Laplacian averaging of the displacement over the
    band (edge weight = number of cells sharing the edge): PETSc Richardson
    iterations with a Jacobi preconditioner on the graph Laplacian, from a
    zero start.

``'none'``
    Only the prescribed nodes move.

The band (:mod:`nagata_snap.smoothing.band`)
    Cells within ``layers`` vertex-neighbour layers of the moved nodes (layer
    1 = cells touching a moved node, layer ``j+1`` = cells touching a node of
    layer ``j``). No mesh is built for it: the system over its free nodes
    is assembled from the owned band cells straight into a distributed
    PETSc matrix (COO set-up of the summed 2x2 / 3x3 node blocks, see
    :class:`_BandSolver`), so the cost follows the number of moved nodes,
    not the mesh. (Building the band as a DOLFINx mesh with ``create_mesh``
    and assembling UFL forms on it cost more than everything else;
    ``create_submesh`` does O(mesh) work.)
    Constrained (Dirichlet) nodes of the band problem: the moved nodes (their
    prescribed displacement), the ``fixed`` nodes, the outer layer of the
    band and, with ``fix_boundary=True`` (default), every exterior-boundary
    node that is not listed as moved (found with DOLFINx, creating the
    facets if the mesh has none; the snapper lists them as ``fixed``
    instead). Constrained nodes keep their input coordinates exactly.

The only per-mesh (not per-band) work is the layer marking and a few cheap
numpy passes over the nodes and the geometry dofmap (node masks, ghost
scatters).

Parallel
    Node masks and coordinates are kept ghost-consistent with
    ``dolfinx.la.vector`` scatters over ``mesh.geometry.index_map()``; the
    owner's coordinates of a node are authoritative. For the same mesh
    (same cells), with or without ghost cells, results agree with a serial
    run to round-off (tests/mpi/snapper_smooth_mpi.py gathers the
    distributed problem and repeats it serially). Note that in 3D
    ``dolfinx.mesh.refine`` itself is partition dependent: Plaza breaks ties
    between equally long face edges by global vertex index, so a serial and
    a parallel refinement of the same coarse mesh can differ in their
    interior diagonals, and the smoothed coordinates then differ too.

:func:`nagata_snap.smoothing.repair.repair` wraps the band smoother in the guard:
check, untangle the neighbourhood of bad cells, slide boundary vertices,
partial moves as the last resort.
"""

from __future__ import annotations

import itertools
import time
from typing import Any

import dolfinx.mesh
import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from nagata_snap.mesh.simplex import cell_columns, cells_touching, compact_nodes, p1_gradients
from nagata_snap.smoothing.band import Band, NodeSync, auto_layers, max_layers, prepare
from nagata_snap.smoothing.kernels import band_blocks, graph_sums

__all__ = ["smooth", "SMOOTH_DEFAULTS", "smooth_options", "Smoother", "add_time"]

#: Default options of :func:`smooth` (``**opts``).
SMOOTH_DEFAULTS: dict[str, Any] = {
    "layers": "auto",       # band width in vertex-neighbour layers (>= 1), or 'auto'
                            # (2, 3 or 4 from the relative displacement, see band.auto_layers)
    "exponent": 1.0,        # stiffening exponent p in E = (V_max/|K|)^p
    "model": "elastic",     # 'elastic' (linear elasticity) or 'harmonic'
    "nu": 0.3,              # Poisson ratio for model='elastic'
    "solver": "cg",         # 'cg' (CG + Jacobi, MUMPS LU if it fails) or 'mumps' (LU)
    "rtol": 1e-12,          # relative tolerance for solver='cg'
    "petsc_options": None,  # extra/overriding KSP options (dict)
    "sweeps": None,         # Jacobi sweeps for 'laplace' (default max(50, 4 layers^2))
    "fix_boundary": True,   # hold every exterior-boundary node not in `moved`
}

_counter = itertools.count()


# ---------------------------------------------------------------------------
# The band's linear system
# ---------------------------------------------------------------------------


def _lame(nu: float) -> tuple[float, float]:
    """Lame parameters ``(mu, lambda)`` for unit Young's modulus and Poisson ratio ``nu``."""
    return 1.0 / (2.0 * (1.0 + nu)), nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def _summed_blocks(G: np.ndarray, w: np.ndarray | None, model: str, nu: float, c: np.ndarray,
                   a: np.ndarray, b: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Node-pair blocks of the P1 stiffness matrix, summed over the cells sharing the pair (numpy).

    The reference formulation of the compiled
    :func:`~nagata_snap.smoothing.kernels.band_blocks` that :func:`_band_matrix`
    uses (``tests/test_kernels.py`` compares them; ``benchmarks/guard_kernels.py`` times them).

    Args:
        G: (nc, nv, gdim) hat-function gradients; w: (nc,) ``E |K|``.
        c, a, b: (m,) cell and local vertex pairs, grouped so that the pairs
            of one node pair are contiguous, the groups starting at ``start``.

    Returns:
        (len(start), gdim, gdim): for each group the sum over its cells of
        the block ``K[c, a, :, b, :]`` of the element matrix of

        * ``'elastic'``: ``int_K E (2 mu eps(u):eps(v) + lambda div u div v)``,
          whose block is ``E |K| (mu (g_a.g_b delta_ij + g_a,j g_b,i) + lambda g_a,i g_b,j)``;
        * ``'harmonic'``: ``E |K| g_a.g_b delta_ij`` (vector Laplacian);
        * ``'graph'``: the graph Laplacian of the cell's edges, per component
          (``nv - 1`` on the diagonal, -1 off it; ``G`` and ``w`` unused).

        Every block is linear in ``P = E |K| g_a (x) g_b`` (``g_a.g_b = tr P``),
        so ``P`` is summed first and the blocks are formed once per node pair.
    """
    d = G.shape[2]
    eye = np.eye(d)
    if c.size == 0:
        return np.zeros((0, d, d))
    if model == "graph":
        return np.add.reduceat(G.shape[1] * (a == b) - 1.0, start)[:, None, None] * eye
    assert w is not None  # the weights of the finite element models
    P = G[c, a][:, :, None] * (w[c, None] * G[c, b])[:, None, :]  # (m, d, d)
    P = np.add.reduceat(P, start, axis=0)
    tr = np.trace(P, axis1=1, axis2=2)[:, None, None]
    if model == "harmonic":
        return tr * eye
    mu, lmbda = _lame(nu)
    return mu * (tr * eye + P.transpose(0, 2, 1)) + lmbda * P


def _apply(G: np.ndarray, w: np.ndarray | None, model: str, nu: float, u: np.ndarray) -> np.ndarray:
    """Element stiffness matrices times element displacements, without forming them.

    ``u``: (nc, nv, gdim) displacement at the cell's vertices. With
    ``H = G^T u`` (the transposed displacement gradient) the elastic
    element action is ``E |K| (mu (G H + G H^T) + lambda tr(H) G)``; the
    harmonic one ``E |K| G H``; the graph one ``nv u - sum_b u_b``.

    Returns:
        (nc, nv, gdim).
    """
    if model == "graph":
        return G.shape[1] * u - u.sum(axis=1, keepdims=True)
    assert w is not None  # the weights of the finite element models
    H = G.transpose(0, 2, 1) @ u  # (nc, d, d): H_ij = sum_b g_b,i u_b,j
    if model == "harmonic":
        return w[:, None, None] * (G @ H)
    mu, lmbda = _lame(nu)
    tr = np.trace(H, axis1=1, axis2=2)
    out = mu * (G @ (H + H.transpose(0, 2, 1))) + lmbda * tr[:, None, None] * G
    return w[:, None, None] * out


def _scalar_coo(rn: np.ndarray, cn: np.ndarray, blocks: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scalar COO arrays of a block matrix, in row-major order.

    ``rn, cn``: (u,) block row / column, sorted by row then column;
    ``blocks``: (u, d, d). Scalar row ``d rn + i``, column ``d cn + j``.
    """
    u, d, _ = blocks.shape
    first = np.flatnonzero(np.r_[True, rn[1:] != rn[:-1]]) if u else np.zeros(0, np.int64)
    count = np.diff(np.r_[first, u])  # blocks per block row
    s = np.repeat(first, count)  # first block of each block's row
    k = np.repeat(count, count)
    i = np.arange(d)
    # entry (block q, i, j) of row d rn + i sits at d^2 s + i d k + d (q - s) + j
    pos = (d * d * s + d * (np.arange(u) - s))[:, None, None] + (d * k)[:, None, None] * i[:, None] + i
    rows = np.empty(u * d * d, dtype=np.int64)
    cols = np.empty_like(rows)
    vals = np.empty(u * d * d)
    rows[pos.ravel()] = np.broadcast_to((d * rn)[:, None, None] + i[:, None], (u, d, d)).ravel()
    cols[pos.ravel()] = np.broadcast_to((d * cn)[:, None, None] + i, (u, d, d)).ravel()
    vals[pos.ravel()] = blocks.ravel()
    return rows, cols, vals


def _stiffness(comm: MPI.Comm, x_ref: np.ndarray, cells: np.ndarray, gdim: int, model: str,
               exponent: float) -> tuple[np.ndarray, np.ndarray | None]:
    """Hat-function gradients ``(nc, nv, gdim)`` and weights ``E |K|`` ``(nc,)`` of band cells (collective).

    ``E = (V_max / |K|)^exponent`` with ``|K|`` the reference measure; for
    ``model='graph'`` the gradients are zeros and the weights None.

    Raises:
        ValueError: a band cell is degenerate in ``x_ref`` (on every process).
    """
    nc, nv = cells.shape
    if model == "graph":
        return np.zeros((nc, nv, gdim)), None
    G, meas = p1_gradients(x_ref, cells, gdim)
    # E = (V_max / |K|)^p; V_max only scales the system (no effect on u)
    vmax = comm.allreduce(float(meas.max(initial=0.0)), op=MPI.MAX)
    with np.errstate(divide="ignore", invalid="ignore"):
        weight = meas * (vmax / np.maximum(meas, 1e-300)) ** float(exponent)
    singular = ~np.isfinite(weight) | ~np.isfinite(G).all(axis=(1, 2)) | (meas <= 0)
    n_bad = comm.allreduce(int(np.count_nonzero(singular)))
    if n_bad:
        raise ValueError(
            f"{n_bad} cells of the smoothing band have zero area / volume in the "
            "reference coordinates x_ref: no stiffness can be built for them")
    return G, weight


def _band_matrix(comm: MPI.Comm, band: Band, G: np.ndarray, weight: np.ndarray | None, model: str,
                 nu: float, gid: np.ndarray, free: np.ndarray, cells: np.ndarray) -> PETSc.Mat:
    """The assembled distributed matrix ``K_ff`` over the band's free nodes (collective).

    ``gid (nc, nv)``: global free-node number of each cell vertex (-1 if
    constrained); ``free = gid >= 0``; ``cells (nc, nv)`` local node
    numbers.  Each process sums the free-free blocks of its cells per node
    pair with the compiled kernel :func:`~nagata_snap.smoothing.kernels.band_blocks`
    (straight into block rows, no per-(cell, pair) temporary), one block
    row per free node of its cells; PETSc's COO set-up adds the rows of
    nodes owned elsewhere to their owners'.
    """

    gdim = G.shape[2]
    nodes = np.unique(cells[free]) if comm.size > 1 else band.own_free
    row_of = np.full(band.gid.size, -1, dtype=np.int64)
    row_of[nodes] = np.arange(nodes.size)
    rows = np.where(free, row_of[cells], -1)
    mu, lmbda = _lame(nu)
    kind = {"elastic": 0, "harmonic": 1, "graph": 2}[model]
    w = np.zeros(G.shape[0]) if weight is None else weight
    indptr, cn, blocks = band_blocks(G, w, rows, np.where(free, gid, -1), kind, mu, lmbda,
                                     int(nodes.size), int(band.n_free_global))
    rn = np.repeat(band.gid[nodes], np.diff(indptr))
    rows_s, cols_s, vals = _scalar_coo(rn, cn, blocks)
    del rn, cn, blocks
    n_loc = band.own_free.size * gdim
    # (petsc4py takes an mpi4py communicator; its stub lists only PETSc.Comm)
    A = PETSc.Mat().create(comm)  # type: ignore[arg-type]
    A.setSizes(((n_loc, PETSc.DETERMINE), (n_loc, PETSc.DETERMINE)))
    A.setType(PETSc.Mat.Type.AIJ)
    # (petsc4py takes integer arrays; its stub says Sequence[int], which ndarray is not)
    A.setPreallocationCOO(rows_s.astype(PETSc.IntType), cols_s.astype(PETSc.IntType))  # type: ignore[arg-type]
    # (petsc4py's stub types addv as InsertMode, but its members are typed int)
    A.setValuesCOO(vals, addv=PETSc.InsertMode.ADD_VALUES)  # type: ignore[arg-type]
    A.assemble()
    return A


def _band_ksp(comm: MPI.Comm, A: PETSc.Mat, model: str, solver: str, rtol: float, sweeps: int,
              petsc_options: dict[str, Any] | None) -> tuple[PETSc.KSP, str]:
    """The PETSc solver of the band system and its kind (``'cg'``, ``'mumps'`` or ``'sweeps'``).

    The options are set under a prefix of their own and removed from the
    global options database afterwards.
    """
    ksp = PETSc.KSP().create(comm)  # type: ignore[arg-type]  # (as for the matrix)
    ksp.setOperators(A)
    prefix = f"nagata_smooth_{next(_counter)}_"
    ksp.setOptionsPrefix(prefix)
    popts: dict[str, Any]
    if model == "graph":
        popts = {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_max_it": int(sweeps),
                 "ksp_norm_type": "none", "ksp_convergence_test": "skip"}
        solver = "sweeps"
    elif solver == "mumps":
        popts = {"ksp_type": "preonly", "pc_type": "lu",
                 "pc_factor_mat_solver_type": "mumps", "ksp_error_if_not_converged": True}
    elif solver == "cg":
        popts = {"ksp_type": "cg", "pc_type": "jacobi", "ksp_rtol": rtol,
                 "ksp_atol": 0.0, "ksp_max_it": 5000, "ksp_error_if_not_converged": True}
    else:
        raise ValueError(f"unknown solver {solver!r} (use 'mumps' or 'cg')")
    popts.update(petsc_options or {})
    opts = PETSc.Options()
    opts.prefixPush(prefix)
    for k, val in popts.items():
        opts.setValue(k, val)
    ksp.setFromOptions()
    for k in popts:
        opts.delValue(k)
    opts.prefixPop()
    return ksp, solver


class _BandSolver:
    """The band system ``K_ff u_f = -K_fc u_c`` (assembled once) and its PETSc solver.

    ``model``: ``'elastic'`` / ``'harmonic'``: stiffened P1 extension, solved
    by CG + Jacobi (MUMPS LU if CG fails) or MUMPS (``solver``);
    ``'graph'``: ``sweeps`` Jacobi sweeps of graph-Laplacian averaging from
    a zero start (PETSc Richardson + Jacobi, no convergence test).
    """

    def __init__(self, mesh: dolfinx.mesh.Mesh, band: Band, x_ref: np.ndarray, model: str, *,
                 exponent: float = 1.0, nu: float = 0.3, solver: str = "cg",
                 rtol: float = 1e-12, petsc_options: dict[str, Any] | None = None,
                 sweeps: int = 50):
        comm = mesh.comm
        gdim = mesh.geometry.dim
        self.gdim = gdim
        self.band = band
        cells = mesh.geometry.dofmaps[0][band.own_cells]
        gid = band.gid[cells]
        keep = (gid >= 0).any(axis=1)  # cells with an unknown
        cells, gid = cells[keep], gid[keep]
        G, weight = _stiffness(comm, x_ref, cells, gdim, model, exponent)
        self.G, self.w, self.model, self.nu = G, weight, model, nu
        self.cells = cells
        self.free = gid >= 0  # (nc, nv)
        # global unknowns of the free vertices of each cell, (c, a, i) order
        free_dof = np.repeat(self.free[:, :, None], gdim, axis=2)
        self.gdof = (gid[:, :, None] * gdim + np.arange(gdim))[free_dof]
        self.A = _band_matrix(comm, band, G, weight, model, nu, gid, self.free, cells)
        self.b, self.x = self.A.createVecRight(), self.A.createVecLeft()
        self.ksp, self.solver = _band_ksp(comm, self.A, model, solver, rtol, sweeps, petsc_options)
        self.n_fallback = 0

    def _switch_to_lu(self) -> None:
        """Replace the iterative solver by MUMPS LU (after CG + Jacobi failed)."""
        self.ksp.setType("preonly")
        pc = self.ksp.getPC()
        pc.setType("lu")
        pc.setFactorSolverType("mumps")
        self.solver = "mumps"
        self.n_fallback += 1

    def solve(self, x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
        """Displacement ``(k, 3)`` of the owned free nodes (``band.own_free``).

        ``x``, ``x_ref``: (n, 3) current and reference coordinates of all
        local nodes; only the constrained nodes of band cells are read (the
        Dirichlet data ``x - x_ref``).
        """
        g = self.gdim
        u = x[self.cells][:, :, :g] - x_ref[self.cells][:, :, :g]  # (nc, nv, g)
        u[self.free] = 0.0
        f = -_apply(self.G, self.w, self.model, self.nu, u)
        self.b.zeroEntries()
        self.b.setValues(self.gdof.astype(PETSc.IntType), f[self.free].reshape(-1),
                         addv=PETSc.InsertMode.ADD_VALUES)  # type: ignore[arg-type]  # (as above)
        self.b.assemble()
        try:
            self.ksp.solve(self.b, self.x)
        except PETSc.Error:
            # CG + Jacobi did not converge (the convergence test is collective,
            # so every process gets here): solve directly instead
            if self.solver != "cg":
                raise
            self._switch_to_lu()
            self.ksp.solve(self.b, self.x)
        out = np.zeros((self.band.own_free.size, 3))
        out[:, :g] = self.x.getArray(readonly=True).reshape(-1, g)
        return out

    def destroy(self) -> None:
        for obj in (self.ksp, self.A, self.b, self.x):
            obj.destroy()


class _GraphSweeps:
    """Jacobi sweeps of graph-Laplacian averaging over the band, matrix-free (``'laplace'``).

    The same iteration as PETSc's Richardson + Jacobi on the band's graph
    Laplacian from a zero start (:func:`_band_ksp`, ``model='graph'``), without
    assembling the matrix: a sweep sets every free node's displacement to
    the average over its band cells of their other vertices' displacements
    (an edge counts once per cell that shares it), constrained nodes giving
    their prescribed ones.  A sweep costs one pass over the band cells (and
    under MPI one reverse and one forward scatter of the sums), so the
    first smoothing of a level costs a few passes over the band.
    """

    solver = "sweeps"
    n_fallback = 0

    def __init__(self, mesh: dolfinx.mesh.Mesh, band: Band, sync: NodeSync, sweeps: int):
        self.gdim = mesh.geometry.dim
        self.band, self.sync, self.sweeps = band, sync, int(sweeps)
        cells = mesh.geometry.dofmaps[0][band.own_cells]
        free = band.gid >= 0  # (n,) free nodes, owned and ghost
        cells = cells[free[cells].any(axis=1)]
        # band nodes numbered compactly (the sweeps work on the band, not the mesh)
        self.nodes, local = compact_nodes(cells, sync.n)
        self.cells = local.astype(np.int64)
        nv = cells.shape[1]
        deg = (nv - 1.0) * np.bincount(self.cells.reshape(-1), minlength=self.nodes.size)
        self.deg = self._total(deg)
        self.free = np.flatnonzero(free[self.nodes])
        self.own_free = np.searchsorted(self.nodes, band.own_free)

    def _total(self, a: np.ndarray) -> np.ndarray:
        """Band-node sums over the processes (``a (k,)`` or ``(k, g)`` over ``nodes``)."""
        if not self.sync.parallel:
            return a
        full = np.zeros((self.sync.n, *a.shape[1:]))
        full[self.nodes] = a
        return self.sync.total(full)[self.nodes]

    def solve(self, x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
        """Displacement ``(k, 3)`` of the owned free nodes (``band.own_free``) after the sweeps."""
        g = self.gdim
        u = x[self.nodes, :g] - x_ref[self.nodes, :g]  # (k, g)
        u[self.free] = 0.0
        for _ in range(self.sweeps):
            acc = self._total(graph_sums(self.cells, u))
            u[self.free] = acc[self.free] / self.deg[self.free, None]
        out = np.zeros((self.own_free.size, 3))
        out[:, :g] = u[self.own_free]
        return out

    def destroy(self) -> None:
        """Nothing to free (no PETSc objects)."""


class Smoother:
    """The band and its solver for one set of options (collective set-up); :meth:`run` smooths.

    Args:
        mesh: the P1 simplex mesh; x_ref: ``(n, 3)`` reference coordinates.
        moved_mask, fixed_mask: ``(n,)`` bool ghost-consistent node masks
            (:func:`~nagata_snap.smoothing.band.prepare`).
        sync: the node sync of the mesh's geometry nodes.
        method: ``'elastic'``, ``'laplace'`` or ``'none'``.
        opts: options as returned by :func:`smooth_options` (``layers`` an
            int or ``(n,)`` per-node ints, not ``'auto'``).
        timings: stage -> seconds, accumulated into (``band``, ``setup``, ``solve``).

    Attributes:
        band: the :class:`~nagata_snap.smoothing.band.Band` (None if nothing moves
            or ``method='none'``); solver: its solver (None without free nodes).
    """

    def __init__(self, mesh: dolfinx.mesh.Mesh, x_ref: np.ndarray, moved_mask: np.ndarray,
                 fixed_mask: np.ndarray, sync: NodeSync, method: str, opts: dict[str, Any],
                 timings: dict[str, float]):
        self.mesh = mesh
        self.x_ref = x_ref
        self.sync = sync
        self.method = method
        self.moved_mask = moved_mask
        self.fixed_mask = fixed_mask
        self.band: Band | None = None
        self.solver: _BandSolver | _GraphSweeps | None = None
        self.timings = timings
        if method not in ("elastic", "laplace", "none"):
            raise ValueError(f"unknown method {method!r} (use 'elastic', 'laplace' or 'none')")
        any_moved = mesh.comm.allreduce(bool(moved_mask[: sync.n_owned].any()),
                                        op=MPI.LOR)
        if method == "none" or not any_moved:
            return
        t0 = time.perf_counter()
        self.band = Band(mesh, moved_mask, fixed_mask, sync, opts["layers"])
        t1 = time.perf_counter()
        add_time(timings, "band", t1 - t0)
        if self.band.n_free_global == 0:
            return
        if method == "elastic":
            self.solver = _BandSolver(mesh, self.band, x_ref, opts["model"],
                                      exponent=opts["exponent"], nu=opts["nu"],
                                      solver=opts["solver"], rtol=opts["rtol"],
                                      petsc_options=opts["petsc_options"])
        else:
            sweeps = opts["sweeps"]
            if sweeps is None:
                sweeps = max(50, 4 * max_layers(opts["layers"], mesh.comm) ** 2)
            if opts["petsc_options"]:  # (options for PETSc's Richardson iteration)
                self.solver = _BandSolver(mesh, self.band, x_ref, "graph", sweeps=sweeps,
                                          petsc_options=opts["petsc_options"])
            else:
                self.solver = _GraphSweeps(mesh, self.band, sync, sweeps)
        add_time(timings, "setup", time.perf_counter() - t1)

    @property
    def cells(self) -> np.ndarray:
        """Local parent cells whose nodes ``run`` may move (empty without a band)."""
        return self.band.cells if self.band is not None else np.zeros(0, dtype=np.int32)

    def run(self, x_cur: np.ndarray) -> np.ndarray:
        """New coordinates (n, 3); constrained nodes keep ``x_cur`` exactly."""
        x_new = np.array(x_cur, dtype=np.float64, copy=True)
        if self.solver is None:
            return x_new
        assert self.band is not None  # a solver is only made for a band
        t0 = time.perf_counter()
        own = self.band.own_free
        x_new[own] = self.x_ref[own] + self.solver.solve(x_cur, self.x_ref)
        x_new = self.sync.forward(x_new)
        add_time(self.timings, "solve", time.perf_counter() - t0)
        return x_new

    def destroy(self) -> None:
        """Free the PETSc objects of the solver."""
        if self.solver is not None:
            self.solver.destroy()


def add_time(timings: dict[str, float] | None, key: str, dt: float) -> None:
    """Add ``dt`` seconds to stage ``key`` of ``timings`` (nothing if None)."""
    if timings is not None:
        timings[key] = timings.get(key, 0.0) + dt


def smooth_options(opts: dict[str, Any]) -> dict[str, Any]:
    """:data:`SMOOTH_DEFAULTS` updated by ``opts`` (``info`` dropped), checked.

    Raises:
        TypeError: an unknown option; ValueError: a bad ``layers``, ``model`` or ``solver``.
    """
    unknown = set(opts) - set(SMOOTH_DEFAULTS) - {"info"}
    if unknown:
        raise TypeError(f"unknown smoothing options: {sorted(unknown)}")
    o = dict(SMOOTH_DEFAULTS)
    o.update({k: v for k, v in opts.items() if k != "info"})
    lay = o["layers"]
    if not (lay == "auto" or (isinstance(lay, (int, np.integer)) and not isinstance(lay, bool)
                              and lay >= 1)):
        raise ValueError(f"layers must be an integer >= 1 or 'auto', not {lay!r}")
    if o["model"] not in ("elastic", "harmonic"):
        raise ValueError(f"unknown model {o['model']!r} (use 'elastic' or 'harmonic')")
    if o["solver"] not in ("cg", "mumps"):
        raise ValueError(f"unknown solver {o['solver']!r} (use 'mumps' or 'cg')")
    return o


# ---------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------


def smooth(mesh: dolfinx.mesh.Mesh, x_ref: np.ndarray, moved: np.ndarray, fixed: np.ndarray,
           method: str = "elastic", **opts) -> np.ndarray:
    """Move interior nodes to follow prescribed boundary displacements.

    Collective on ``mesh.comm``. Does not modify ``mesh`` or any input array.

    Args:
        mesh: ``dolfinx.mesh.Mesh`` with P1 triangles (2D) or tetrahedra (3D)
            whose ``geometry.x`` already holds the prescribed new positions of
            the ``moved`` nodes (at least on the owning rank; the owner's value
            is used for ghosts).
        x_ref: (n, 3) float64 reference coordinates of all local geometry
            nodes (owned + ghost) -- the straight refined mesh before
            snapping. Length unit of the mesh.
        moved: (k,) int32 local geometry-node indices with a prescribed new
            position (listing a node on any rank that holds it is enough).
        fixed: (m,) int32 local geometry-node indices that must not move
            (other boundary nodes). A node in both lists counts as moved.
        method: ``'elastic'`` (default), ``'laplace'`` or ``'none'``.
        **opts: see :data:`SMOOTH_DEFAULTS`:

            * ``layers`` (int or ``'auto'``, default ``'auto'``): band width
              in vertex-neighbour layers (for ``'elastic'`` and
              ``'laplace'``); ``'auto'``: 2, 3 or 4 from the largest
              displacement relative to the shortest edge of the cells it
              touches (<= 0.1, <= 0.3, above);
            * ``exponent`` (float, 1.0): stiffening exponent ``p`` of
              ``E = (V_max/|K|)^p``;
            * ``model`` ('elastic' | 'harmonic'), ``nu`` (Poisson ratio);
            * ``solver`` ('cg' | 'mumps'): ``'cg'`` (default) is CG +
              Jacobi to ``rtol``, and MUMPS LU on the same system if CG does
              not converge (the band is a few cell layers thick, so diagonal
              scaling is enough: CG + GAMG is slower, its set-up costs more
              than it saves here); ``'mumps'`` is LU
              directly; ``petsc_options`` override either;
            * ``sweeps`` (int): Jacobi sweeps for ``'laplace'``;
            * ``fix_boundary`` (bool, True): also hold every exterior-boundary
              node not listed as moved (creates the mesh's facets if it has
              none: O(mesh); pass the boundary nodes as ``fixed`` and
              ``False`` to avoid that);
            * ``info`` (dict): if given, filled with ``timings`` (stage ->
              seconds), ``band_cells``, ``band_nodes``, ``band_free_nodes``
              (global counts), ``solver_fallbacks`` (0 or 1: CG failed, LU
              used), ``layers`` (the band width used).

    Returns:
        (n, 3) float64 new coordinates of all local nodes (ghost rows equal
        to the owner's). Moved and fixed nodes, and all nodes outside the
        band, are bit-for-bit equal to ``mesh.geometry.x`` (owner's value).
    """
    info = opts.get("info")
    o = smooth_options(opts)
    timings: dict[str, float] = {}
    sync, x_ref, moved_mask, fixed_mask = prepare(mesh, x_ref, moved, fixed,
                                                    bool(o["fix_boundary"]))
    x_cur = sync.forward(mesh.geometry.x)
    if o["layers"] == "auto":
        cells = mesh.geometry.dofmaps[0]
        disp = np.where(moved_mask[:, None], x_cur - x_ref, 0.0)
        o["layers"] = auto_layers(x_ref, disp, cells,
                                   cells_touching(np.any(disp != 0.0, axis=1), cell_columns(cells)), sync)
    sm = Smoother(mesh, x_ref, moved_mask, fixed_mask, sync, method, o, timings)
    try:
        x_new = sm.run(x_cur)
    finally:
        sm.destroy()
    if info is not None:
        info["timings"] = timings
        if sm.band is not None:
            info["band_cells"] = sm.band.n_cells_global
            info["band_nodes"] = sm.band.n_nodes_global
            info["band_free_nodes"] = sm.band.n_free_global
        info["solver_fallbacks"] = getattr(sm.solver, "n_fallback", 0)
        info["layers"] = max_layers(o["layers"], mesh.comm)
    return x_new
