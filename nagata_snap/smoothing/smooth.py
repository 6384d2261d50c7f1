"""Interior smoothing after boundary snapping, and the inverted-cell guard.

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

The band
    Cells within ``layers`` vertex-neighbour layers of the moved nodes (layer
    1 = cells touching a moved node, layer ``j+1`` = cells touching a node of
    layer ``j``). No mesh is built for it: the system over its free nodes
    is assembled from the owned band cells straight into a distributed
    PETSc matrix (COO set-up of the summed 2x2 / 3x3 node blocks, see
    :class:`_BandSolver`), so the cost follows the number of moved nodes,
    not the mesh. (Building the band as a DOLFINx mesh with ``create_mesh``
    and assembling UFL forms on it cost about 4 us per band cell, more than
    everything else; ``create_submesh`` does O(mesh) work.)
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

import dolfinx
import dolfinx.la
import dolfinx.mesh
import mpi4py.MPI
import numpy as np
from petsc4py import PETSc

from nagata_snap.mesh.boundary import check_p1_simplex
from nagata_snap.mesh.simplex import inverse_small
from nagata_snap.smoothing.quality import _columns, _touching, edge_length_range

__all__ = ["smooth", "SMOOTH_DEFAULTS"]

#: Default options of :func:`smooth` (``**opts``).
SMOOTH_DEFAULTS: dict[str, Any] = {
    "layers": "auto",       # band width in vertex-neighbour layers (>= 1), or 'auto'
                            # (2, 3 or 4 from the relative displacement, see _auto_layers)
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
# MPI helpers on the geometry-node index map
# ---------------------------------------------------------------------------


class _NodeSync:
    """Ghost-consistency helpers for arrays over the nodes of an index map."""

    def __init__(self, imap):
        self.imap = imap
        self.comm = imap.comm
        self.n_owned = imap.size_local
        self.n = imap.size_local + imap.num_ghosts
        self.parallel = imap.comm.size > 1
        self._vec: dict[int, Any] = {}

    def _v(self, bs: int):
        if bs not in self._vec:
            self._vec[bs] = dolfinx.la.vector(self.imap, bs)
        return self._vec[bs]

    def any(self, mask: np.ndarray) -> np.ndarray:
        """Collective OR: a node is True everywhere if True on any rank."""
        if not self.parallel:
            return np.asarray(mask, dtype=bool).copy()
        v = self._v(1)
        v.array[:] = np.asarray(mask, dtype=np.float64)
        v.scatter_reverse(dolfinx.la.InsertMode.add)
        v.scatter_forward()
        return v.array > 0.5

    def forward(self, a: np.ndarray) -> np.ndarray:
        """Copy of ``a`` (n, bs) / (n,) with ghost rows replaced by the owner's."""
        a = np.array(a, dtype=np.float64, copy=True)
        if not self.parallel:
            return a
        bs = 1 if a.ndim == 1 else a.shape[1]
        v = self._v(bs)
        v.array[:] = a.reshape(-1)
        v.scatter_forward()
        return v.array.reshape(a.shape).copy()

    def reverse_add(self, a: np.ndarray) -> np.ndarray:
        """Sum of the rows of ``a`` over all ranks, valid on owned rows."""
        a = np.asarray(a, dtype=np.float64)
        if not self.parallel:
            return a.copy()
        bs = 1 if a.ndim == 1 else a.shape[1]
        v = self._v(bs)
        v.array[:] = a.reshape(-1)
        v.scatter_reverse(dolfinx.la.InsertMode.add)
        return v.array.reshape(a.shape).copy()


def _mask(n: int, idx) -> np.ndarray:
    m = np.zeros(n, dtype=bool)
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    if idx.size:
        if idx.min() < 0 or idx.max() >= n:
            raise IndexError("node index out of range of the local geometry nodes")
        m[idx] = True
    return m


#: ``layers='auto'``: (largest relative displacement, band layers); above the
#: last threshold the band has AUTO_LAYERS_MAX layers.
AUTO_LAYERS = ((0.1, 2), (0.3, 3))
AUTO_LAYERS_MAX = 4



def _auto_layers(comm, x_ref: np.ndarray, disp: np.ndarray, cells: np.ndarray,
                 touched: np.ndarray, sync: _NodeSync) -> np.ndarray:
    """Band width of every node for the prescribed displacement ``disp`` (n, 3) (collective).

    ``touched`` (nc,) bool: the cells with a displaced node (a superset does
    no harm: cells without one have relative displacement 0).

    The relative displacement of a cell is the largest prescribed
    displacement of its nodes over its shortest reference edge; a displaced
    node takes the largest over its cells: below 0.1 (the usual case after
    refinement, where the snapping distance is O(h^2)) two layers around it
    are enough to spread the move, below 0.3 three, otherwise four (as for
    the first levels of a very coarse polygon).  So one far-moving vertex
    widens the band only around itself.  The repair goes further where
    cells still invert.

    Returns:
        (n,) int: layers around each displaced node (0 elsewhere), ghost-consistent.
    """
    n = x_ref.shape[0]
    dn = np.linalg.norm(disp, axis=1)
    node_rel = np.zeros(n)
    sel = np.flatnonzero(touched)
    if sel.size:
        sub = cells[sel]
        hmin, _ = edge_length_range(x_ref, sub, sub.shape[1] - 1)
        dmax = dn[sub].max(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(hmin > 0, dmax / hmin, np.inf)
        for k in range(sub.shape[1]):
            np.maximum.at(node_rel, sub[:, k], rel)
    # (a process sees only some cells of a node: a threshold passed on any widens)
    moving = sync.any(dn > 0)
    out = np.where(moving, AUTO_LAYERS[0][1], 0)
    wider = [layers for _, layers in AUTO_LAYERS[1:]] + [AUTO_LAYERS_MAX]
    for (limit, _), layers in zip(AUTO_LAYERS, wider):
        out = np.where(moving & sync.any(node_rel > limit), layers, out)
    return out


def _expand(cells: np.ndarray, mark: np.ndarray, layers, sync: _NodeSync,
            cols: list[np.ndarray] | None = None):
    """Grow a node mask by ``layers`` cell layers (collective).

    ``layers``: an int, or ``(n,)`` ints per node of ``mark`` (each such
    node grows by its own number of layers: the widest start first, the
    others join when as many steps remain as they need).

    Returns (mark_k, mark_{k-1}, cells_in) with cells_in the cells touching a
    node of mark_{k-1}.
    """
    cols = _columns(cells) if cols is None else cols
    per_node = np.ndim(layers) > 0
    total = int(np.max(layers, initial=0)) if per_node else int(layers)
    if per_node:
        total = int(sync.comm.allreduce(total, op=mpi4py.MPI.MAX))
        need = np.where(mark, layers, 0)
        mark = need >= total
    prev = mark
    cin = np.zeros(cells.shape[0], dtype=bool)
    for step in range(total):
        if per_node:
            mark = mark | (need >= total - step)
        cin = _touching(mark, cols)
        new = mark.copy()
        new[cells[cin].reshape(-1)] = True
        new = sync.any(new)
        prev, mark = mark, new
    return mark, prev, cin


def _max_layers(layers, comm) -> int:
    """Band width of an int or per-node ``layers`` (the largest over all processes)."""
    if np.ndim(layers) == 0:
        return int(layers)
    return int(comm.allreduce(int(np.max(layers, initial=0)), op=mpi4py.MPI.MAX))


# ---------------------------------------------------------------------------
# Band and its linear system
# ---------------------------------------------------------------------------


def _exterior_nodes(mesh, sync: _NodeSync) -> np.ndarray:
    """(n,) bool: nodes on the exterior boundary of ``mesh`` (collective).

    Creates the facets and the facet-to-cell connectivity if the mesh has
    none (O(mesh)); :class:`~nagata_snap.snapper.Snapper` lists its boundary
    nodes as ``fixed`` instead, which costs nothing.
    """
    tdim = mesh.topology.dim
    mesh.topology.create_entities(tdim - 1)
    mesh.topology.create_connectivity(tdim - 1, tdim)
    ext = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    nodes = dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, ext)
    return sync.any(_mask(sync.n, nodes))


def _p1_gradients(x: np.ndarray, cells: np.ndarray, gdim: int) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of the P1 hat functions and cell measures of affine simplices.

    Args:
        x: (n, 3) node coordinates; cells: (nc, gdim + 1) nodes of each cell.

    Returns:
        ``(G (nc, gdim + 1, gdim), measure (nc,))``: ``G[c, a]`` is the
        gradient of the hat function of local vertex ``a`` in cell ``c``
        (1 / length unit); ``measure`` is the area / volume.
    """
    X = x[cells][:, :, :gdim]
    J = X[:, 1:] - X[:, :1]  # (nc, gdim, gdim), rows = edge vectors from vertex 0
    Jinv, det = inverse_small(J)
    G = np.empty((len(cells), gdim + 1, gdim))
    G[:, 1:] = Jinv.transpose(0, 2, 1)  # grad lambda_a = column a - 1 of J^-1
    with np.errstate(invalid="ignore"):  # degenerate cells: inf / nan, rejected by callers
        G[:, 0] = -G[:, 1:].sum(axis=1)
    return G, np.abs(det) / (2.0 if gdim == 2 else 6.0)


def _lame(nu: float) -> tuple[float, float]:
    """Lame parameters ``(mu, lambda)`` for unit Young's modulus and Poisson ratio ``nu``."""
    return 1.0 / (2.0 * (1.0 + nu)), nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def _summed_blocks(G: np.ndarray, w: np.ndarray | None, model: str, nu: float, c: np.ndarray,
                   a: np.ndarray, b: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Node-pair blocks of the P1 stiffness matrix, summed over the cells sharing the pair.

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
    P = G[c, a][:, :, None] * (w[c, None] * G[c, b])[:, None, :]  # (m, d, d)
    P = np.add.reduceat(P, start, axis=0)
    tr = np.trace(P, axis1=1, axis2=2)[:, None, None]
    if model == "harmonic":
        return tr * eye
    mu, lmbda = _lame(nu)
    return mu * (tr * eye + P.transpose(0, 2, 1)) + lmbda * P


def _apply(G: np.ndarray, w: np.ndarray, model: str, nu: float, u: np.ndarray) -> np.ndarray:
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
    H = G.transpose(0, 2, 1) @ u  # (nc, d, d): H_ij = sum_b g_b,i u_b,j
    if model == "harmonic":
        return w[:, None, None] * (G @ H)
    mu, lmbda = _lame(nu)
    tr = np.trace(H, axis1=1, axis2=2)
    out = mu * (G @ (H + H.transpose(0, 2, 1))) + lmbda * tr[:, None, None] * G
    return w[:, None, None] * out


class _Band:
    """Cells within ``layers`` of the moved nodes and the unknowns on them (collective).

    No mesh is built for the band: its system is assembled from the parent
    mesh's cells straight into a PETSc matrix whose unknowns are the band's
    free nodes, numbered contiguously by their owners. So the work follows
    the band, not the mesh, and there is no per-band mesh, function space or
    form set-up (``dolfinx.mesh.create_mesh`` of the band and the DOLFINx
    assembly cost about 2 us per band cell each).

    Attributes:
        cells: (m,) int32 local parent cells of the band (owned and ghost);
            every node the smoother can move is only in cells of this list.
        own_cells: the owned ones (each cell is assembled once, by its owner).
        own_free: (k,) local indices of the owned free nodes (in a band cell,
            not constrained: neither moved, fixed nor in the band's outer
            layer), in global order.
        gid: (n,) int64 global number of each free node (-1 elsewhere).
        n_cells_global, n_nodes_global, n_free_global: band size.
    """

    def __init__(self, mesh, moved_mask, fixed_mask, sync, layers, cols=None):
        if np.ndim(layers) == 0 and layers < 1:
            raise ValueError("layers must be >= 1")
        comm = mesh.comm
        cells = mesh.geometry.dofmaps[0]
        mark, prev, cin = _expand(cells, moved_mask, layers, sync, cols)
        self.cells = np.flatnonzero(cin).astype(np.int32)
        n_own_cells = mesh.topology.index_map(mesh.topology.dim).size_local
        self.own_cells = self.cells[self.cells < n_own_cells]
        in_band = np.zeros(sync.n, dtype=bool)
        in_band[cells[self.cells].reshape(-1)] = True
        in_band = sync.any(in_band)
        free = in_band & ~(moved_mask | fixed_mask | (mark & ~prev))
        self.own_free = np.flatnonzero(free[: sync.n_owned])
        offset = comm.exscan(self.own_free.size) if comm.size > 1 else 0
        gid = np.full(sync.n, -1.0)
        gid[self.own_free] = (offset or 0) + np.arange(self.own_free.size)
        self.gid = sync.forward(gid).astype(np.int64)
        self.n_cells_global = comm.allreduce(int(self.own_cells.size))
        self.n_nodes_global = comm.allreduce(int(np.count_nonzero(in_band[: sync.n_owned])))
        self.n_free_global = comm.allreduce(int(self.own_free.size))


def _scalar_coo(rn: np.ndarray, cn: np.ndarray, blocks: np.ndarray):
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


class _BandSolver:
    """The band system ``K_ff u_f = -K_fc u_c`` (assembled once) and its PETSc solver.

    ``model``: ``'elastic'`` / ``'harmonic'``: stiffened P1 extension, solved
    by CG + Jacobi (MUMPS LU if CG fails) or MUMPS (``solver``);
    ``'graph'``: ``sweeps`` Jacobi sweeps of graph-Laplacian averaging from
    a zero start (PETSc Richardson + Jacobi, no convergence test).
    """

    def __init__(self, mesh, band: _Band, x_ref: np.ndarray, model: str, *,
                 exponent: float = 1.0, nu: float = 0.3, solver: str = "cg",
                 rtol: float = 1e-12, petsc_options: dict | None = None, sweeps: int = 50):
        comm = mesh.comm
        gdim = mesh.geometry.dim
        self.gdim = gdim
        self.band = band
        cells = mesh.geometry.dofmaps[0][band.own_cells]
        gid = band.gid[cells]
        keep = (gid >= 0).any(axis=1)  # cells with an unknown
        cells, gid = cells[keep], gid[keep]
        nc, nv = cells.shape
        if model == "graph":
            G, weight = np.zeros((nc, nv, gdim)), None
        else:
            G, meas = _p1_gradients(x_ref, cells, gdim)
            # E = (V_max / |K|)^p; V_max only scales the system (no effect on u)
            vmax = comm.allreduce(float(meas.max(initial=0.0)), op=mpi4py.MPI.MAX)
            with np.errstate(divide="ignore", invalid="ignore"):
                weight = meas * (vmax / np.maximum(meas, 1e-300)) ** float(exponent)
            singular = ~np.isfinite(weight) | ~np.isfinite(G).all(axis=(1, 2)) | (meas <= 0)
            n_bad = comm.allreduce(int(np.count_nonzero(singular)))
            if n_bad:
                raise ValueError(
                    f"{n_bad} cells of the smoothing band have zero area / volume in the "
                    "reference coordinates x_ref: no stiffness can be built for them")
        self.G, self.w, self.model, self.nu = G, weight, model, nu
        self.cells = cells
        self.free = gid >= 0  # (nc, nv)
        # matrix: the blocks of free-free vertex pairs, summed per node pair
        # (sorted keys, so PETSc's COO set-up sees each entry once, in order)
        c, a, b = np.nonzero(self.free[:, :, None] & self.free[:, None, :])
        n_free = band.n_free_global
        key = gid[c, a] * n_free + gid[c, b]
        order = np.argsort(key)
        key = key[order]
        start = np.flatnonzero(np.r_[key.size > 0, key[1:] != key[:-1]])
        blocks = _summed_blocks(G, weight, model, nu, c[order], a[order], b[order], start)
        rn, cn = np.divmod(key[start], n_free)
        rows, cols, vals = _scalar_coo(rn, cn, blocks)
        # global unknowns of the free vertices of each cell, (c, a, i) order
        free_dof = np.repeat(self.free[:, :, None], gdim, axis=2)
        self.gdof = (gid[:, :, None] * gdim + np.arange(gdim))[free_dof]
        n_loc = band.own_free.size * gdim
        A = PETSc.Mat().create(comm)
        A.setSizes([[n_loc, PETSc.DETERMINE], [n_loc, PETSc.DETERMINE]])
        A.setType(PETSc.Mat.Type.AIJ)
        A.setPreallocationCOO(rows.astype(PETSc.IntType), cols.astype(PETSc.IntType))
        A.setValuesCOO(vals, addv=PETSc.InsertMode.ADD_VALUES)
        A.assemble()
        self.A = A
        self.b, self.x = A.createVecs()
        ksp = PETSc.KSP().create(comm)
        ksp.setOperators(A)
        prefix = f"nagata_smooth_{next(_counter)}_"
        ksp.setOptionsPrefix(prefix)
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
            opts[k] = val
        ksp.setFromOptions()
        for k in popts:
            del opts[k]
        opts.prefixPop()
        self.ksp = ksp
        self.solver = solver
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
                         addv=PETSc.InsertMode.ADD_VALUES)
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

    def destroy(self):
        for obj in (self.ksp, self.A, self.b, self.x):
            obj.destroy()


class _Smoother:
    """Band + solver for one set of options; ``run`` maps prescribed to new x."""

    def __init__(self, mesh, x_ref, moved_mask, fixed_mask, sync, method, opts, timings,
                 cols=None):
        self.mesh = mesh
        self.x_ref = x_ref
        self.sync = sync
        self.method = method
        self.moved_mask = moved_mask
        self.fixed_mask = fixed_mask
        self.band = None
        self.solver = None
        self.timings = timings
        if method not in ("elastic", "laplace", "none"):
            raise ValueError(f"unknown method {method!r} (use 'elastic', 'laplace' or 'none')")
        any_moved = mesh.comm.allreduce(bool(moved_mask[: sync.n_owned].any()),
                                        op=mpi4py.MPI.LOR)
        if method == "none" or not any_moved:
            return
        t0 = time.perf_counter()
        self.band = _Band(mesh, moved_mask, fixed_mask, sync, opts["layers"], cols)
        t1 = time.perf_counter()
        _acc(timings, "band", t1 - t0)
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
                sweeps = max(50, 4 * _max_layers(opts["layers"], mesh.comm) ** 2)
            self.solver = _BandSolver(mesh, self.band, x_ref, "graph", sweeps=sweeps,
                                      petsc_options=opts["petsc_options"])
        _acc(timings, "setup", time.perf_counter() - t1)

    @property
    def cells(self) -> np.ndarray:
        """Local parent cells whose nodes ``run`` may move (empty without a band)."""
        return self.band.cells if self.band is not None else np.zeros(0, dtype=np.int32)

    def run(self, x_cur: np.ndarray) -> np.ndarray:
        """New coordinates (n, 3); constrained nodes keep ``x_cur`` exactly."""
        x_new = np.array(x_cur, dtype=np.float64, copy=True)
        if self.solver is None:
            return x_new
        t0 = time.perf_counter()
        own = self.band.own_free
        x_new[own] = self.x_ref[own] + self.solver.solve(x_cur, self.x_ref)
        x_new = self.sync.forward(x_new)
        _acc(self.timings, "solve", time.perf_counter() - t0)
        return x_new

    def destroy(self):
        if self.solver is not None:
            self.solver.destroy()


def _acc(timings: dict | None, key: str, dt: float):
    if timings is not None:
        timings[key] = timings.get(key, 0.0) + dt


def _prepare(mesh, x_ref, moved, fixed, fix_boundary: bool):
    """Validate inputs, build masks (ghost-consistent) and the node sync.

    With ``fix_boundary`` every exterior-boundary node that is not moved is fixed.
    """
    check_p1_simplex(mesh)
    sync = _NodeSync(mesh.geometry.index_map())
    n = sync.n
    x_ref = np.asarray(x_ref, dtype=np.float64)
    if x_ref.shape != (n, 3):
        raise ValueError(f"x_ref must have shape {(n, 3)}, got {x_ref.shape}")
    moved_mask = sync.any(_mask(n, moved))
    fixed_mask = sync.any(_mask(n, fixed))
    if fix_boundary:
        fixed_mask |= _exterior_nodes(mesh, sync)
    return sync, x_ref, moved_mask, fixed_mask & ~moved_mask


def _options(opts: dict) -> dict:
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


def smooth(mesh, x_ref: np.ndarray, moved: np.ndarray, fixed: np.ndarray,
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
              scaling is enough: 3x faster than CG + GAMG on 1e6 tetrahedra,
              whose set-up costs more than it saves here); ``'mumps'`` is LU
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
    o = _options(opts)
    timings: dict[str, float] = {}
    sync, x_ref, moved_mask, fixed_mask = _prepare(mesh, x_ref, moved, fixed,
                                                    bool(o["fix_boundary"]))
    x_cur = sync.forward(mesh.geometry.x)
    if o["layers"] == "auto":
        cells = mesh.geometry.dofmaps[0]
        disp = np.where(moved_mask[:, None], x_cur - x_ref, 0.0)
        o["layers"] = _auto_layers(mesh.comm, x_ref, disp, cells,
                                   _touching(np.any(disp != 0.0, axis=1), _columns(cells)), sync)
    sm = _Smoother(mesh, x_ref, moved_mask, fixed_mask, sync, method, o, timings)
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
        info["layers"] = _max_layers(o["layers"], mesh.comm)
    return x_new
