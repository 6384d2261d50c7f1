"""Simultaneous untangling and shape optimisation of a small simplex mesh.

The repair (:mod:`nagata_snap.smoothing.repair`) hands this module the neighbourhood
of the cells that a linear smoother left inverted or degenerate, as plain
arrays (coordinates, cells, which nodes may move); it returns new
coordinates.  Under MPI the arrays are each process's part of the
neighbourhood (its local nodes and the cells it owns, with the
:class:`~nagata_snap.smoothing.halo.Layout` of the nodes): see
"Distributed" below.

Objective (Escobar, Rodriguez, Montenegro, Montero, Gonzalez-Yuste,
"Simultaneous untangling and smoothing of tetrahedral meshes", CMAME 192
(2003) 2775-2787).  For a cell with edge matrix ``A`` (columns
``x_j - x_0``, ``d x d``) and target edge matrix ``W``, ``S = A W^-1`` is the
affine map from the target cell to the cell, ``sigma = det S`` its volume
ratio.  Knupp's algebraic shape measure, the inverse mean ratio
``eta(S) = |S|_F^2 / (d sigma^(2/d))`` (1 when ``S`` is a similarity, infinite
when the cell is flat), is made finite for inverted cells by replacing
``sigma`` with Escobar's regularised determinant::

    h(sigma) = (sigma + sqrt(sigma^2 + 4 delta^2)) / 2,      eta_delta = |S|^2 / (d h^(2/d))

``h`` is positive, increasing and ``h -> sigma`` for ``sigma >> delta``, so
minimising ``F(x) = sum_K eta_delta(S_K)`` over the free nodes pushes inverted
cells (``h ~ delta^2 / |sigma|``, huge ``eta``) through to positive volume and
then improves the worst shapes; with a small ``delta`` a valid mesh is a
barrier-protected minimum.  ``delta`` follows the smallest volume ratio of the
current mesh, ``delta^2 = eps (eps - sigma_min)`` while
``sigma_min < eps`` (Escobar et al.), and ``delta = DELTA_MIN`` once the cells are
valid.  The target ``W`` is the cell's straight refined shape (not the
equilateral one, Knupp's target-matrix idea): an anisotropic boundary layer
keeps its aspect ratio, and the straight mesh is the optimum where nothing
moved.

Gradient (exact): with ``r = sqrt(sigma^2 + 4 delta^2)`` and
``cof(S) = d sigma / d S`` (the cofactor matrix),
``d eta / d S = 2 S / (d h^(2/d)) - 2 eta cof(S) / (d r)`` and
``d eta / d A = (d eta / d S) W^-T``; vertex ``j >= 1`` of the cell gets column
``j - 1`` of it, vertex 0 minus their sum.

Hessian (exact, for Newton's method): with ``a = 2 h^(-2/d) / d`` and
``b = 2 eta / (d r)``, so that ``d eta / d S = a S - b cof(S)``,
``d^2 eta / d S^2 = a I - (2 a / (d r)) (S (x) C + C (x) S)
+ (2 b / (d r) + b sigma / r^2) C (x) C - b d cof / d S`` (``C = cof S``;
``d cof_cj / d S_kl = e_ckm e_jln S_mn`` in 3D, ``e_ck e_jl`` in 2D, ``e`` the
permutation symbol), and ``d S_cj / d x_vc = B_vj`` (``B_vj = W^-1_(v-1)j``,
``B_0j = -sum_k W^-1_kj``), so the cell's Hessian in its vertex coordinates
is ``B H_S B^T`` per pair of components.

Minimiser: Newton's method over all moving nodes at once (the sparse
Hessian assembled from the cells into a PETSc matrix and factorised by
MUMPS, LDL^T), with Levenberg damping where the Hessian is not positive
definite and an Armijo line search; near the minimum it converges
quadratically, so the result is the minimum to round-off.  Variables are
scaled by each node's shortest reference edge (cells of very different
sizes, e.g. boundary layers, then weigh alike).  With ``shrink`` (the repair's
optimise stage) the final round's active set shrinks: the nodes whose Newton
step fell below :data:`SHRINK_STEP` stay, and the problem is set up again on
the others and their neighbours, so the late iterations cost what the few
nodes near the worst cells need, not the whole neighbourhood.  Nodes that slide on the
geometry enter through a tangent basis ``T`` (``x = p + s T t``,
``|t| <=`` :data:`SLIDE_STEP` edge lengths); the caller projects them back
onto the geometry and calls again (:func:`optimise` with ``slide``).

Distributed (owner computes): each process evaluates the energy, gradient
and cell Hessians of the cells it owns; a node's variables belong to the
process that owns the node (the rows of a distributed PETSc AIJ matrix,
numbered by owner, factorised by MUMPS on all processes; when no cell
couples two processes' variables, i.e. no process has a ghost moving node,
the matrix is block diagonal by process and each process factorises its
block alone, sequential MUMPS in a block-Jacobi preconditioner: exact, and
without the messages of the distributed factorisation), ghost copies of
the moving nodes get their owner's variables every evaluation and send
their gradient and Hessian-diagonal contributions back to it
(:class:`~nagata_snap.smoothing.halo.Halo`: only the problem's shared
nodes are exchanged).  Every decision (gradient tolerance, Levenberg
damping, descent test, Armijo acceptance, relative decrease, the rounds of
``delta``) is taken from collective reductions that give the same bits on
every process (:mod:`nagata_snap.smoothing.halo`), so every process takes
the same branch and a parallel run performs the serial run's iterations up
to the order of floating-point sums (a node's contributions from cells on
different processes, the energy's partial sums, MUMPS's distributed
factorisation).  A converged result therefore agrees with the serial one
to round-off times the conditioning of the Newton systems; a result that
stopped at the iteration limit (:attr:`OptimiseResult.converged` False:
e.g. cells that cannot be untangled) depends on the round-off of every
iteration and may differ by more.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import mpi4py.MPI  # noqa: F401  (must precede petsc4py)
import numpy as np
from petsc4py import PETSc

from nagata_snap.mesh.simplex import cell_columns, edge_matrices, inverse_small
from nagata_snap.smoothing import kernels
from nagata_snap.smoothing.halo import (
    Halo,
    Layout,
    anywhere,
    first_index,
    gathered,
    in_rank_order,
    maximum,
    minimum,
    total,
)

__all__ = ["targets", "energy", "energy_numpy", "optimise", "OptimiseResult", "volume_ratio_min", "EPS",
           "DELTA_MIN", "SLIDE_STEP"]

#: ``eps`` of the regularisation schedule ``delta^2 = eps (eps - sigma_min)``
#: (volume ratios are relative to the target cell, so ``eps`` is dimensionless).
EPS = 1e-2
#: ``delta`` once every cell is valid: ``h(sigma)`` differs from ``sigma`` by
#: less than ``DELTA_MIN^2 / sigma``, and a flat cell costs ``|S|^2 / DELTA_MIN^(2/d)``.
DELTA_MIN = 1e-4
#: Newton: gradient tolerance (scaled variables) and largest step per node
#: and iteration (edge lengths).
GTOL = 1e-10
MAX_STEP = 4.0
#: Newton: relative decrease of ``F`` per iteration below which a round stops
#: (final round at ``delta = DELTA_MIN``; untangling rounds).  Near the
#: minimum a Newton step lowers ``F`` by about ``g^T H^-1 g / 2``, so 1e-9
#: relative leaves the nodes within about ``sqrt(2e-9 F / lambda_min)`` of the
#: minimum, far below the quality differences that matter.
FTOL_FINAL = 1e-9
FTOL_UNTANGLE = 1e-10
#: Newton: a step whose predicted decrease ``-g^T p`` is below this fraction of
#: ``|F|`` ends the round as converged: Armijo's test (a decrease of ``1e-4 t
#: g^T p``) would compare differences below the round-off of ``F`` (a sum
#: over up to 1e5 cells), and its 20 halvings fail or pass by round-off.
SLOPE_RTOL = 1e-12
#: Largest tangential move of a sliding node per call, in units of its
#: shortest edge (the tangent plane is a good model of the surface there).
SLIDE_STEP = 0.3
#: Shrinking active set (:func:`optimise` with ``shrink``): a node whose last
#: Newton step in the final round was below ``SHRINK_STEP`` edge lengths has
#: converged; once fewer than ``SHRINK_FRACTION`` of the moving nodes are
#: still moving, the problem is set up again on those and their neighbours.
SHRINK_STEP = 1e-4
SHRINK_FRACTION = 0.5


def targets(x_ref: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Inverse target matrices ``W^-1`` ``(m, d, d)`` of the reference cells.

    Args:
        x_ref: ``(n, d)`` reference coordinates; cells: ``(m, d + 1)``.

    Raises:
        ValueError: a reference cell is degenerate (no target shape).
    """
    winv, det = inverse_small(_edges(x_ref, cells))
    if not np.all(np.isfinite(winv)) or np.any(det == 0):
        raise ValueError("degenerate reference cells in the untangling neighbourhood")
    return winv


def _edges(x: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Edge matrices ``A`` ``(m, d, d)``, column ``j`` = ``x_{j+1} - x_0`` (``x (n, d)``)."""
    return np.swapaxes(edge_matrices(x, cells, x.shape[1]), 1, 2)


class _Cells:
    """Cells with their inverse targets as flat ``(m,)`` entries (set up once per problem).

    The kernels work on flat arrays, one per matrix entry (``S[c][j]``:
    component ``c``, target edge ``j``): several times faster than batched
    ``(m, 3, 3)`` products for these tiny matrices.
    """

    def __init__(self, cells: np.ndarray, winv: np.ndarray, n: int):
        self.n, self.d = n, winv.shape[1]
        self.cols = cell_columns(cells)
        self.w = [[np.ascontiguousarray(winv[:, i, j]) for j in range(self.d)]
                  for i in range(self.d)]
        self.B = np.concatenate([-winv.sum(axis=1, keepdims=True), winv], axis=1)  # (m, d+1, d)
        self.cells = cells
        self.cells64 = np.ascontiguousarray(cells, dtype=np.int64)
        self.ones = np.ones(cells.shape, dtype=np.float64)

    def shape(self, x: np.ndarray) -> list[list[np.ndarray]]:
        """Entries of ``S = A W^-1``."""
        d, w = self.d, self.w
        S = []
        for c in range(d):
            xc = np.ascontiguousarray(x[:, c])
            p0 = xc.take(self.cols[0])
            a = [xc.take(self.cols[k + 1]) - p0 for k in range(d)]
            S.append([sum(a[k] * w[k][j] for k in range(d)) for j in range(d)])
        return S


def _det_cof(S: list[list[np.ndarray]]) -> tuple[np.ndarray, list[list[np.ndarray]]]:
    """``det S`` and the cofactor matrix ``d det / d S``, from entries."""
    if len(S) == 2:
        cof = [[S[1][1], -S[1][0]], [-S[0][1], S[0][0]]]
    else:
        cof = [[S[(c + 1) % 3][(j + 1) % 3] * S[(c + 2) % 3][(j + 2) % 3]
                - S[(c + 1) % 3][(j + 2) % 3] * S[(c + 2) % 3][(j + 1) % 3] for j in range(3)]
               for c in range(3)]
    return sum(S[c][0] * cof[c][0] for c in range(len(S))), cof


def energy(x: np.ndarray, cells: np.ndarray | None, winv: np.ndarray | None, delta: float,
           grad: bool = True, prepared: _Cells | None = None, hessian: bool = False) -> tuple[Any, ...]:
    """``F = sum eta_delta(S_K)``, its gradient, the volume ratios, and the cell Hessians.

    The compiled kernels of :mod:`nagata_snap.smoothing.kernels`; the same
    arguments and results as :func:`energy_numpy` (to rounding).
    """
    if prepared is None:
        if cells is None or winv is None:
            raise ValueError("energy needs cells and winv, or prepared")
        prepared = _Cells(cells, winv, x.shape[0])
    xc = np.ascontiguousarray(x, dtype=np.float64)
    if not grad:
        F, sigma = kernels.energy_value(xc, prepared.cells64, prepared.B, float(delta))
        return float(F), None, sigma
    F, g, sigma, Hx = kernels.energy_terms(xc, prepared.cells64, prepared.B, float(delta),
                                           bool(hessian), prepared.ones)
    return (float(F), g, sigma, Hx) if hessian else (float(F), g, sigma)


def energy_numpy(x: np.ndarray, cells: np.ndarray | None, winv: np.ndarray | None, delta: float,
                 grad: bool = True, prepared: _Cells | None = None,
                 hessian: bool = False) -> tuple[Any, ...]:
    """``F = sum eta_delta(S_K)``, its gradient, the volume ratios, and the cell Hessians (numpy).

    The reference formulation of :func:`energy`, batched over the cells.

    Args:
        x: ``(n, d)`` coordinates; cells: ``(m, d + 1)``; winv: ``(m, d, d)``
            from :func:`targets`; delta: regularisation (dimensionless, > 0).
        prepared: the same cells and targets as a ``_Cells`` (then ``cells``
            and ``winv`` are not read).
        hessian: also return the cell Hessians (module docstring).

    Returns:
        ``(F (float), dF/dx (n, d) or None, sigma (m,))``, and with ``hessian`` a
        fourth item ``(m, d + 1, d, d + 1, d)``: second derivatives of each
        cell's ``eta`` with respect to its vertex coordinates.
    """
    if prepared is None:
        if cells is None or winv is None:
            raise ValueError("energy needs cells and winv, or prepared")
        prepared = _Cells(cells, winv, x.shape[0])
    cc = prepared
    d = cc.d
    S = cc.shape(x)
    sigma, cof = _det_cof(S)
    r = np.sqrt(sigma * sigma + 4.0 * delta * delta)
    # h = (sigma + r) / 2 = 2 delta^2 / (r - sigma): the second form has no cancellation
    h = 0.5 * (sigma + r)
    neg = sigma < 0
    h[neg] = 2.0 * delta * delta / (r[neg] - sigma[neg])
    hp = h ** (-2.0 / d)
    eta = sum(S[c][j] * S[c][j] for c in range(d) for j in range(d)) * hp / d
    F = float(eta.sum())
    if not grad:
        return F, None, sigma
    a, b = (2.0 / d) * hp, (2.0 / d) * eta / r
    g = np.empty((cc.n, d))
    for c in range(d):
        dS = [a * S[c][j] - b * cof[c][j] for j in range(d)]
        dA = [sum(dS[j] * cc.w[k][j] for j in range(d)) for k in range(d)]  # vertex k + 1
        gc = np.bincount(cc.cols[0], weights=-sum(dA), minlength=cc.n)
        for k in range(d):
            gc += np.bincount(cc.cols[k + 1], weights=dA[k], minlength=cc.n)
        g[:, c] = gc
    if not hessian:
        return F, g, sigma
    Sm = np.stack([np.stack(row, axis=1) for row in S], axis=1)  # (m, d, d)
    Cm = np.stack([np.stack(row, axis=1) for row in cof], axis=1)
    HS = _hessian_S(Sm, Cm, sigma, r, a, b).transpose(0, 1, 3, 2, 4)  # (m, c, e, j, l)
    B = cc.B[:, None, None]  # (m, 1, 1, d + 1, d)
    Hx = (B @ HS @ np.swapaxes(B, 3, 4)).transpose(0, 3, 1, 4, 2)  # (m, v, c, w, e)
    return F, g, sigma, Hx


def _cofactor_derivative(d: int) -> np.ndarray:
    """Constant ``K (d^4, d^2)`` with ``d cof / d S = K S`` in 3D (``e_ckp e_jlq``), ``(d^4,)`` in 2D."""
    if d == 2:
        e = np.array([[0.0, 1.0], [-1.0, 0.0]])
        return np.einsum("ck,jl->cjkl", e, e).reshape(-1)
    e = np.zeros((3, 3, 3))
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        e[i, j, k], e[i, k, j] = 1.0, -1.0
    return np.einsum("ckp,jlq->cjklpq", e, e).reshape(81, 9)


_DCOF = {2: _cofactor_derivative(2), 3: _cofactor_derivative(3)}


def _hessian_S(S: np.ndarray, C: np.ndarray, sigma: np.ndarray, r: np.ndarray, a: np.ndarray,
               b: np.ndarray) -> np.ndarray:
    """``d^2 eta / dS^2`` ``(m, d, d, d, d)`` (module docstring)."""
    m, d, _ = S.shape
    if d == 2:
        dC = np.broadcast_to(_DCOF[2], (m, 16))
    else:
        dC = S.reshape(m, 9) @ _DCOF[3].T
    Sf, Cf = S.reshape(m, d * d), C.reshape(m, d * d)
    SC = Sf[:, :, None] * Cf[:, None, :]
    H = ((2.0 * b / (d * r) + b * sigma / r**2)[:, None, None] * Cf[:, :, None] * Cf[:, None, :]
         - (2.0 * a / (d * r))[:, None, None] * (SC + SC.transpose(0, 2, 1))
         - b[:, None, None] * dC.reshape(m, d * d, d * d))
    H[:, np.arange(d * d), np.arange(d * d)] += a[:, None]
    return H.reshape(m, d, d, d, d)


@dataclasses.dataclass
class OptimiseResult:
    """What :func:`optimise` did.

    Attributes:
        x: ``(n, d)`` new coordinates (fixed nodes bit-for-bit unchanged; with a
            :class:`~nagata_snap.smoothing.halo.Layout`, every local copy of a
            moving node, owned or ghost, holds its owner's value).
        sigma_min: smallest volume ratio of the active cells at ``x`` (over all processes).
        evaluations: objective evaluations; rounds: regularisation rounds;
            shrinks: times the final round's active set was set up anew (``shrink``).
        converged: the final round (valid cells, ``delta = DELTA_MIN``) ended at a
            minimum (a tolerance of Newton's method met, or no descent step left),
            not at the iteration limit.  A result that did not converge depends on
            the round-off of every iteration (a serial and a parallel run may
            differ by more than round-off); a converged one only on its input's.
    """

    x: np.ndarray
    sigma_min: float
    evaluations: int
    rounds: int
    converged: bool = True
    shrinks: int = 0


def optimise(x: np.ndarray, cells: np.ndarray, winv: np.ndarray, free: np.ndarray,
             scale: np.ndarray, *, slide: np.ndarray | None = None,
             basis: np.ndarray | None = None, max_rounds: int = 6,
             max_iterations: int = 40, layout: Layout | None = None,
             shrink: bool = False) -> OptimiseResult:
    """Minimise ``F`` over the free (and sliding) nodes, from an invalid start if need be.

    Serial (``layout`` None): the arrays are the whole problem.  Distributed
    (collective on ``layout.comm``): the arrays are this process's local
    nodes (owned and ghost, as numbered by ``layout``) and the cells it
    owns (each cell of the problem on exactly one process); node arrays
    (``x``, ``free``, ``scale``, the sliding nodes and their bases) must
    agree on every copy of a node.  Each process evaluates its cells, the
    gradient and the Hessian are summed onto the owners of the nodes (a
    distributed PETSc matrix, factorised by MUMPS), and every decision is
    taken from collective reductions (:mod:`nagata_snap.smoothing.halo`), so
    every process takes the same branches and a parallel run the serial
    run's iterations, up to the order of the sums.

    Args:
        x: ``(n, d)`` start coordinates.
        cells: ``(m, d + 1)`` cells; winv: ``(m, d, d)`` (:func:`targets`).
        free: ``(n,)`` bool, nodes that move freely.
        scale: ``(n,)`` length of each node's variables (its shortest edge).
        slide: ``(k,)`` indices of nodes moving in their tangent space only
            (not in ``free``); basis: ``(k, d, d - 1)`` orthonormal tangent
            vectors (zero columns where the space has fewer dimensions).
        max_rounds: regularisation rounds (``delta`` updated from the
            smallest volume ratio between rounds; they stop early when a
            round no longer raises it: the cells cannot be untangled here).
        max_iterations: Newton iterations of the final (valid, ``delta =
            DELTA_MIN``) round; the untangling rounds get half as many.
        layout: owned and ghost nodes of a distributed problem (None: serial).
        shrink: an active set that shrinks in the final round (not with
            ``slide``): once fewer than :data:`SHRINK_FRACTION` of the moving
            nodes took a step above :data:`SHRINK_STEP` edge lengths, only
            those and the moving nodes sharing a cell with them move on (the
            problem set up again on them; the decision is collective, and a
            node's copies agree).  The others stay within about that step of
            their minimum; the iterations cost what the nodes still moving need.

    Returns:
        :class:`OptimiseResult`; the result is a deterministic function of
        the inputs (and of the partition).
    """
    x = np.array(x, dtype=float)
    layout = Layout.serial(len(x)) if layout is None else layout
    pb = _Problem(x, cells, winv, free, scale, slide, basis, layout)
    shrink = shrink and slide is None
    extra, shrinks = 0, 0  # (evaluations and set-ups of the shrunken problems)
    try:
        if pb.total_size == 0:
            return OptimiseResult(x, pb.sigma_min(pb.z0), 0, 0)
        z, rounds, smin, converged, written = pb.z0, 0, pb.sigma_min(pb.z0), False, False
        while rounds < max_rounds:
            rounds += 1
            delta = max(np.sqrt(EPS * (EPS - smin)) if smin < EPS else 0.0, DELTA_MIN)
            final = delta == DELTA_MIN
            its = max_iterations if final else max_iterations // 2
            z, done, active = _newton(pb, z, delta, its, SHRINK_STEP if shrink and final else 0.0)
            written = active is not None
            if active is not None:  # the final round goes on over the nodes still moving
                x[pb.nodes] = pb.coords(pb.with_ghosts(z))
                done, n, k = _shrinking(pb, x, active, cells, winv, scale, layout, delta, its)
                z, shrinks, extra = pb.variables(x), shrinks + n, extra + k
            prev, smin = smin, pb.sigma_min(z)
            if smin > 0 and final:
                converged = done
                break  # valid and converged
            if smin < 0 and smin <= prev + 0.05 * abs(prev):
                break  # no progress on the worst cell
        if not written:  # (after shrinking, x holds the result already)
            x[pb.nodes] = pb.coords(pb.with_ghosts(z))
    finally:
        pb.destroy()
    return OptimiseResult(x, smin, pb.count + extra, rounds, converged, shrinks)


def _shrinking(pb: _Problem, x: np.ndarray, active: np.ndarray, cells: np.ndarray, winv: np.ndarray,
               scale: np.ndarray, layout: Layout, delta: float, max_iterations: int
               ) -> tuple[bool, int, int]:
    """The rest of a final Newton round on shrinking sets of nodes (``x (n, d)`` updated in place).

    ``active`` (the mask of ``pb``'s moving nodes to go on with, from
    :func:`_newton`): each set-up moves those from ``x``, at most
    ``max_iterations`` Newton iterations, until Newton stops without asking
    to shrink again (each set-up has fewer than :data:`SHRINK_FRACTION` of
    the nodes of the one before).  Returns ``(stopped, set-ups, evaluations)``.
    """
    shrinks, count = 0, 0
    sub = pb
    nxt: np.ndarray | None = active
    while nxt is not None:
        moving = np.zeros(x.shape[0], dtype=bool)
        moving[sub.nodes[sub.moving]] = nxt
        if sub is not pb:
            count += sub.count
            sub.destroy()
        sub, shrinks = _Problem(x, cells, winv, moving, scale, None, None, layout), shrinks + 1
        z, done, nxt = _newton(sub, sub.z0, delta, max_iterations, SHRINK_STEP)
        x[sub.nodes] = sub.coords(sub.with_ghosts(z))
    count += sub.count
    sub.destroy()
    return done, shrinks, count


def _newton(pb: _Problem, z: np.ndarray, delta: float, max_iterations: int, shrink: float = 0.0
            ) -> tuple[np.ndarray, bool, np.ndarray | None]:
    """Damped Newton iterations on ``F`` at fixed ``delta`` (Levenberg damping, Armijo steps).

    Stops at a gradient below ``GTOL`` (scaled variables), at a Newton step
    that predicts a decrease below :data:`SLOPE_RTOL` relative, or when an
    iteration lowers ``F`` by less than ``ftol`` relative: :data:`FTOL_FINAL`
    in the final round (``delta = DELTA_MIN``), :data:`FTOL_UNTANGLE` in an
    untangling round, whose minimum is only a step towards the next ``delta``;
    or when no damping gives a descent step.  ``z`` is this process's
    variables; every test is a collective reduction.  Returns ``(z, stopped,
    active)``: ``stopped`` unless the iterations ran out; with ``shrink > 0``,
    Newton stops for :func:`_shrinking` once the nodes whose last step exceeded
    ``shrink`` (scaled variables) and their neighbours are fewer than
    :data:`SHRINK_FRACTION` of the moving nodes, ``active`` their mask
    (:meth:`_Problem.still_moving`); else None.
    """
    ftol = FTOL_FINAL if delta == DELTA_MIN else FTOL_UNTANGLE
    F, g, hv = pb.evaluate(z, delta)
    mu = 0.0
    for _ in range(max_iterations):  # (a stop is a return)
        # projected Newton: variables at a bound that the gradient pushes out stay there
        held = ((z <= pb.lo) & (g > 0)) | ((z >= pb.hi) & (g < 0))
        g = np.where(held, 0.0, g)
        if pb.max_abs(g) <= GTOL:
            return z, True, None
        step = None
        for _ in range(12):  # damping until a descent direction with an Armijo step
            p = pb.solve(hv, mu, -g, held)
            finite, big, slope = pb.step_stats(g, p)
            if finite:
                if big > MAX_STEP:  # at most MAX_STEP edge lengths per node and iteration
                    p *= MAX_STEP / big
                    slope *= MAX_STEP / big
                if -SLOPE_RTOL * abs(F) <= slope <= 0.0:  # (a descent too small for F to resolve)
                    return z, True, None
                if slope < 0:
                    step = _armijo(pb, z, p, F, slope, delta)
                    if step is not None:
                        break
            mu = max(10.0 * mu, 1e-6)
        if step is None:
            return z, True, None
        z_new, F_new = step
        done = F - F_new <= ftol * abs(F)
        mu = mu / 10.0 if mu > 1e-6 else 0.0
        if done:
            return z_new, True, None
        if shrink > 0:
            active = pb.still_moving(z_new - z, shrink)
            if active is not None:
                return z_new, True, active
        z = z_new
        F, g, hv = pb.evaluate(z, delta)
    return z, False, None


def _armijo(pb: _Problem, z: np.ndarray, p: np.ndarray, F: float, slope: float, delta: float
            ) -> tuple[np.ndarray, float] | None:
    """``(z_new, F_new)`` of the first halving of the step that decreases ``F`` enough, or None."""
    t = 1.0
    for _ in range(20):
        zn = pb.clip(z + t * p)
        Fn = pb.value(zn, delta)
        if np.isfinite(Fn) and Fn <= F + 1e-4 * t * slope:
            return zn, Fn
        t *= 0.5
    return None


class _Problem:
    """This process's cells with a moving node, renumbered compactly, and the scaled variables ``z``.

    Every moving node has ``d`` variables: ``x = x0 + E z_node`` with ``E = s I``
    (free nodes, ``s`` their scale) or ``s T`` (sliding nodes; unused
    columns are zero, their variables stay 0).  The problem's nodes are the
    nodes of its cells and every local moving node; the moving ones (its
    variable blocks, ``z_all``) are the owned ones first (this process's
    variables ``z``, in the distributed matrix's rows), then the ghost ones
    (their owners' values, :meth:`with_ghosts`).
    """

    def __init__(self, x: np.ndarray, cells: np.ndarray, winv: np.ndarray, free: np.ndarray,
                 scale: np.ndarray, slide: np.ndarray | None, basis: np.ndarray | None,
                 layout: Layout):
        d = x.shape[1]
        self.d, self.comm = d, layout.comm
        si = np.zeros(0, np.int64) if slide is None else np.asarray(slide, dtype=np.int64)
        moving = np.asarray(free, dtype=bool).copy()
        moving[si] = True
        if self.comm.size == 1:  # (distributed: the caller's cells hold every moving node somewhere)
            in_cells = np.zeros(moving.size, dtype=bool)
            in_cells[cells.reshape(-1)] = True
            moving &= in_cells
        act = moving[cells].any(axis=1)
        self.nodes = np.union1d(cells[act], np.flatnonzero(moving))  # sorted: owned nodes first
        local = np.searchsorted(self.nodes, cells[act])
        self.cells = _Cells(local.reshape(-1, cells.shape[1]), winv[act], self.nodes.size)
        self.x0 = x[self.nodes]
        mv = moving[self.nodes]
        self.var = np.where(mv, np.cumsum(mv) - 1, -1)  # variable block of each node (in z_all)
        self.moving = np.flatnonzero(mv)
        self.n_own = int(np.count_nonzero(self.nodes[self.moving] < layout.n_owned))
        self._tangents(si, basis)
        self.s = scale[self.nodes]
        self.E = self.R * self.s[:, None, None]  # x = x0 + s R z
        self._sv = np.ascontiguousarray(self.s[self.cells.cells], dtype=np.float64)  # (m, d + 1)
        self.Em = self.E[self.moving]
        lim = self.lim[self.moving].ravel()
        self.size, self.size_all = self.n_own * d, self.moving.size * d
        self.lo, self.hi = -lim[: self.size], lim[: self.size]
        self.bounded = anywhere(self.comm, bool(np.isfinite(lim).any()))  # (sliding nodes)
        self.dead = lim[: self.size] == 0.0  # variables that never move (slide dims without tangent)
        self.z0 = np.zeros(self.size)
        self.count = 0
        self._exchange_plan(layout)
        self.total_size = int(total(self.comm, float(self.size)))
        self._matrix()

    def _tangents(self, si: np.ndarray, basis: np.ndarray | None) -> None:
        """``R (nodes, d, d)`` (identity or tangent basis of the moving nodes), bounds, sliding nodes."""
        d = self.d
        self.R = np.zeros((self.nodes.size, d, d))
        self.R[self.moving] = np.eye(d)
        self.lim = np.full((self.nodes.size, d), np.inf)
        self.sliding = np.zeros(self.nodes.size, dtype=bool)
        if not si.size:
            return
        if basis is None:
            raise ValueError("sliding nodes need their tangent basis (basis=)")
        pos = np.searchsorted(self.nodes, si)
        T = np.zeros((si.size, d, d))
        T[:, :, : basis.shape[2]] = basis
        self.R[pos] = T
        live = np.linalg.norm(T, axis=1) > 0.5
        self.lim[pos] = np.where(live, SLIDE_STEP, 0.0)
        self.sliding[pos] = True

    def _exchange_plan(self, layout: Layout) -> None:
        """The halo of the ghost moving nodes and the global number of every variable."""
        d = self.d
        self.halo = Halo(layout, self.nodes[self.moving[self.n_own:]])
        self._recv = self.var[np.searchsorted(self.nodes, self.halo.recv_nodes)]
        self._send = self.var[np.searchsorted(self.nodes, self.halo.send_nodes)]
        block = np.empty(self.moving.size, dtype=np.int64)
        block[: self.n_own] = first_index(self.comm, self.n_own) + np.arange(self.n_own)
        block[self._recv] = self.halo.exchange(block[self._send])
        self.gidx = (block[:, None] * d + np.arange(d)).ravel()  # global index of each z_all entry

    def _matrix(self) -> None:
        """The Hessian's pattern (cell blocks, then the owned diagonal) and its MUMPS solver."""
        d = self.d
        cv = np.ascontiguousarray(self.var[self.cells.cells], dtype=np.int64)  # (m, d + 1)
        # (the distinct d x d blocks, each entry once: the cell Hessians are summed into them by
        # a compiled pass per evaluation, so PETSc's COO assembly sees no duplicates)
        self._slot, brow, bcol = kernels.hessian_blocks(cv, self.moving.size)
        self._nblocks, self._brow, self._bcol = brow.size, brow, bcol
        # blocks with a sliding node's row or column: rotated into its tangent basis
        slid = self.sliding[self.moving]
        self._rot = np.flatnonzero(slid[brow] | slid[bcol])
        self._Rm = np.ascontiguousarray(self.R[self.moving])
        cd = np.arange(d)
        self._r = (brow[:, None, None] * d + cd[None, :, None] + 0 * cd[None, None, :]).ravel()
        self._c = (bcol[:, None, None] * d + 0 * cd[None, :, None] + cd[None, None, :]).ravel()
        on_diag = self._r == self._c
        self._diag_src, self._diag_pos = np.flatnonzero(on_diag), self._r[on_diag]
        self._ksp = None
        if not self.total_size:
            return
        own = self.gidx[: self.size]
        comm: Any = PETSc.COMM_SELF if self.comm.size == 1 else self.comm  # (petsc4py takes mpi4py's)
        A = PETSc.Mat().create(comm)
        A.setSizes(((self.size, self.total_size), (self.size, self.total_size)))
        A.setType(PETSc.Mat.Type.AIJ)
        A.setPreallocationCOO(np.r_[self.gidx[self._r], own].astype(PETSc.IntType),
                              np.r_[self.gidx[self._c], own].astype(PETSc.IntType))
        # (petsc4py's stub types the option as Mat.Option, but its members are typed int)
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)  # type: ignore[arg-type]
        ksp = PETSc.KSP().create(comm)
        ksp.setOperators(A)
        ksp.setType("preonly")
        pc = ksp.getPC()
        # no ghost moving node on any process: no cell couples two processes' variables, the
        # matrix is block diagonal by process and each block is factorised where it lives
        self._blocks = self.comm.size > 1 and not anywhere(self.comm, bool(self.halo.recv_nodes.size))
        self._sub: Any = None
        if self._blocks:
            pc.setType("bjacobi")  # (one block per process; set up at the first solve)
        else:
            ksp.setErrorIfNotConverged(True)  # (a failed factorisation raises, on every process)
            pc.setType("cholesky")
            pc.setFactorSolverType("mumps")
        self._A, self._ksp = A, ksp
        self._b, self._x = A.createVecRight(), A.createVecLeft()

    def _block_solver(self) -> None:
        """The process's diagonal block factorised by sequential MUMPS (LDL^T), set up once."""
        assert self._ksp is not None
        self._ksp.setUp()
        (sub,) = self._ksp.getPC().getBJacobiSubKSP()
        sub.setType("preonly")
        spc = sub.getPC()
        spc.setType("cholesky")
        spc.setFactorSolverType("mumps")
        sub.getOperators()[0].setOption(PETSc.Mat.Option.SYMMETRIC, True)  # type: ignore[arg-type]
        self._sub = spc

    def with_ghosts(self, z: np.ndarray) -> np.ndarray:
        """``z_all``: this process's variables, then its ghost moving nodes' (from their owners; collective)."""
        d = self.d
        za = np.empty(self.size_all)
        za[: self.size] = z
        if self.halo.parallel:
            zb = za.reshape(-1, d)
            zb[self._recv] = self.halo.exchange(zb[self._send])
        return za

    def _to_owners(self, a: np.ndarray) -> np.ndarray:
        """Owned rows of ``a (moving, ...)`` plus their ghost copies' rows on the other processes."""
        if self.halo.parallel:
            np.add.at(a, self._send, self.halo.exchange_back(a[self._recv]))
        return a[: self.n_own]

    def still_moving(self, dz: np.ndarray, tol: float) -> np.ndarray | None:
        """The moving nodes to go on with after the step ``dz (size,)`` (collective), or None.

        Those whose step exceeds ``tol`` (scaled variables) and the moving
        nodes sharing a cell with them, as a mask over the moving nodes
        (owned and ghost, alike on every copy), if fewer than
        :data:`SHRINK_FRACTION` of all moving nodes; else None.
        """
        act = np.zeros(self.moving.size, dtype=np.int8)
        act[: self.n_own] = np.abs(dz).reshape(-1, self.d).max(axis=1, initial=0.0) > tol
        if self.halo.parallel:
            act[self._recv] = self.halo.exchange(act[self._send])
        on = np.zeros(self.nodes.size, dtype=bool)
        on[self.moving] = act > 0
        hit = np.zeros(self.nodes.size, dtype=bool)
        hit[self.cells.cells[on[self.cells.cells].any(axis=1)]] = True
        mark = np.zeros(self.moving.size, dtype=np.int8)
        mark[: self.n_own] = self._to_owners(hit[self.moving].astype(np.int8)) > 0  # (ghost marks count)
        if self.halo.parallel:
            mark[self._recv] = self.halo.exchange(mark[self._send])
        n_next = total(self.comm, float(np.count_nonzero(mark[: self.n_own])))
        return mark > 0 if 0 < n_next < SHRINK_FRACTION * self.total_size / self.d else None

    def variables(self, x: np.ndarray) -> np.ndarray:
        """This process's variables ``z`` of the coordinates ``x (n, d)`` (free nodes only)."""
        own = self.moving[: self.n_own]
        dx = x[self.nodes[own]] - self.x0[own]
        return (dx / self.s[own, None]).ravel()

    def coords(self, za: np.ndarray) -> np.ndarray:
        xx = self.x0.copy()
        xx[self.moving] += np.einsum("kcd,kd->kc", self.Em, za.reshape(-1, self.d))
        return xx

    def clip(self, z: np.ndarray) -> np.ndarray:
        return np.clip(z, self.lo, self.hi)

    def max_abs(self, a: np.ndarray) -> float:
        return maximum(self.comm, float(np.abs(a).max(initial=0.0)))

    def step_stats(self, g: np.ndarray, p: np.ndarray) -> tuple[bool, float, float]:
        """``(p finite everywhere, max |p|, g . p)`` over all processes (one collective)."""
        finite = bool(np.all(np.isfinite(p)))
        loc = np.array([0.0 if finite else 1.0, float(np.abs(p).max(initial=0.0)) if finite else 0.0,
                        float(g @ p) if finite else 0.0])
        parts = gathered(self.comm, loc)
        return (not parts[:, 0].any(), float(parts[:, 1].max()), float(in_rank_order(parts[:, 2])))

    def value(self, z: np.ndarray, delta: float) -> float:
        self.count += 1
        F = energy(self.coords(self.with_ghosts(z)), None, None, delta, grad=False, prepared=self.cells)[0]
        return float(total(self.comm, F))

    def evaluate(self, z: np.ndarray, delta: float) -> tuple[float, np.ndarray, np.ndarray]:
        """``(F, gradient (size,), Hessian values)`` in the variables ``z`` (values for :meth:`solve`)."""
        self.count += 1
        cc = self.cells
        # (the cell Hessians times s_v s_w, summed into the matrix blocks in cell order)
        F, g, Hb = kernels.energy_blocks(self.coords(self.with_ghosts(z)), cc.cells64, cc.B,
                                         float(delta), self._sv, self._slot, self._nblocks)
        gz = self._to_owners(np.einsum("kcd,kc->kd", self.Em, g[self.moving])).ravel()
        if self._rot.size:  # blocks of sliding nodes: into their tangent bases
            kernels.rotate_blocks(Hb, self._Rm, self._brow, self._bcol, self._rot)
        hv = Hb.reshape(-1)
        gz[self.dead] = 0.0
        return float(total(self.comm, F)), gz, hv

    def solve(self, hv: np.ndarray, mu: float, rhs: np.ndarray, held: np.ndarray) -> np.ndarray:
        """Solve ``(H + mu diag(H)) p = rhs`` (dead and ``held`` variables: identity rows; collective)."""
        d = self.d
        held_all = np.zeros(self.size_all, dtype=bool)
        held_all[: self.size] = held
        if self.halo.parallel and self.bounded:  # the owners' held variables, on their ghost copies
            hb = held_all.reshape(-1, d).view(np.int8)
            hb[self._recv] = self.halo.exchange(hb[self._send])
        if held_all.any():  # (a dead variable's entries are 0 already: its tangent column is)
            hv = np.where(held_all[self._r] | held_all[self._c], 0.0, hv)
        fixed = self.dead | held
        extra = fixed.astype(np.float64)
        if mu > 0:  # Levenberg: mu diag(H) (the owners' sums of the diagonal entries)
            diag = np.bincount(self._diag_pos, weights=hv[self._diag_src], minlength=self.size_all)
            diag = self._to_owners(diag.reshape(-1, d)).ravel()
            extra += mu * np.maximum(diag, 1e-12) * ~fixed
        assert self._ksp is not None  # solve is only called on a problem with variables
        # (petsc4py's stub: addv typed InsertMode but its members int; arrays where it says Sequence)
        self._A.setValuesCOO(np.r_[hv, extra], addv=PETSc.InsertMode.INSERT_VALUES)  # type: ignore[arg-type]
        self._A.assemble()
        self._b.setArray(rhs)  # type: ignore[arg-type]
        try:
            self._ksp.setOperators(self._A)
            if self._blocks and self._sub is None:
                self._block_solver()
            self._ksp.solve(self._b, self._x)
            if self._blocks and int(self._sub.getFailedReason()) != 0:  # (a local failure:
                return np.full(self.size, np.nan)  # the caller's collective test sees it)
        except PETSc.Error:
            return np.full(self.size, np.nan)
        return self._x.getArray().copy()

    def destroy(self) -> None:
        if self._ksp is not None:
            for obj in (self._ksp, self._A, self._b, self._x):
                obj.destroy()
            self._ksp = None

    def sigma_min(self, z: np.ndarray) -> float:
        """Smallest volume ratio of the problem's cells (over all processes; inf without cells)."""
        x = np.ascontiguousarray(self.coords(self.with_ghosts(z)))
        s = np.inf
        if self.cells.cols[0].size:
            s = float(kernels.energy_value(x, self.cells.cells64, self.cells.B, DELTA_MIN)[1].min())
        return minimum(self.comm, s)


def volume_ratio_min(x: np.ndarray, cells: np.ndarray, winv: np.ndarray) -> float:
    """Smallest volume ratio ``det(A W^-1)`` of the cells (inf without cells)."""
    if cells.shape[0] == 0:
        return np.inf
    return float(_det_cof(_Cells(cells, winv, x.shape[0]).shape(x))[0].min())
