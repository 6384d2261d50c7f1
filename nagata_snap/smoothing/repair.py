"""The guard: smooth, check, repair bad cells where they are, report what was left short.

After the snapper moved the new boundary vertices onto the geometry,
:func:`repair` returns a valid mesh (no inverted cell, none below the
quality floor) or raises :class:`InvertedCellsError`.  It runs these stages
and stops at the first that leaves no bad cell:

``smooth`` (:func:`_linear`)
    The requested smoother of :mod:`nagata_snap.smoothing.smooth` on the band
    of cells around the moved vertices: the start of every later stage.
    With ``method='elastic'`` (the default) the cost follows the trouble:
    first ``first_sweeps`` (:data:`FIRST_SWEEPS`) Jacobi sweeps of
    graph-Laplacian averaging over the whole band (the ``'laplace'``
    smoother, a few sparse matrix-vector products); only if that leaves
    bad or poor cells is the stiffened linear-elastic extension solved, on
    the band of the moved vertices near them (:data:`ELASTIC_NEAR` layers
    around the bad / poor cells; the other moved vertices and the swept
    interior are its Dirichlet data).  After a refinement the snapping
    moves are O(h^2), so usually no cell is bad or poor and the level
    costs the sweeps and the checks (``benchmarks/guard_quality.py``
    compares the changed cells' quality with and without the elastic
    solve everywhere).
``optimise`` (:func:`_optimise`)
    No cell is bad (after the smooth stage, or after the untangle / slide
    stages below), but some changed cells are *poor* (their mean ratio fell
    below :data:`POOR_RATIO` of the straight cell's): the optimiser below
    moves the nodes near the poor cells (:data:`OPTIMISE_LAYERS`), in passes
    over the cells that became poor in the pass before (an active set that
    shrinks, :data:`OPTIMISE_PASSES`), each kept if it helps; within a pass
    the Newton iterations go on over the nodes still moving only
    (:func:`~nagata_snap.smoothing.untangle.optimise` with ``shrink``).  Not with
    ``method='none'`` (no interior motion unless a cell is bad).
``untangle`` (:func:`_untangle`)
    The interior nodes of the neighbourhood of the bad cells (:data:`UNTANGLE_LAYERS`
    vertex layers, wider while that helps, within a size budget;
    :class:`~nagata_snap.smoothing.neighbourhood.Neighbourhood`)
    are moved by the simultaneous untangling and shape optimisation
    of :mod:`nagata_snap.smoothing.untangle` (a regularised mean-ratio objective that
    accepts an inverted start; a linear extension of the boundary
    displacement cannot untangle).  Skipped for the slide stage when a bad
    cell has only constrained vertices or a turned-over constrained facet.
``slide`` (:func:`_slide`)
    If bad cells remain (their nodes are constrained: all on the boundary,
    or pinned by it), snapped boundary vertices within :data:`SLIDE_LAYERS`
    of them also move, tangentially on the geometry (:mod:`nagata_snap.smoothing.slide`;
    needs ``slide=``, which :class:`~nagata_snap.snapper.Snapper` passes): they
    stay on the geometry and their records are updated.
``partial`` (:func:`_partial`)
    The last resort, always reported: the moved vertices near the remaining
    bad cells get a blame weight ``w`` (1 within ``radius`` layers, tapering
    to 0 over :data:`TAPER_LAYERS` more) and the displacement fractions
    ``alpha(t) = a - (1 - t) w (a - min_fraction)``; a bisection on ``t``
    keeps the largest valid ``t``, the neighbourhood being re-optimised for
    each trial; rounds double the blamed radius.  As a final round every
    moved vertex is blamed and the linear smoother of the first stage
    (already set up) is re-solved; with ``min_fraction = 0`` that ends at
    the straight mesh, which is valid.
``InvertedCellsError``
    If ``min_fraction`` forbids the moves that would be needed.

Each stage works on the cells it can change only: the band, or the
neighbourhood of the bad cells, whose set-up (marks, halo, targets, scales) is
reused by the attempts of the untangle and slide stages.  The check
(:class:`_Guard.check`) looks only at cells that a stage could have changed,
so it is O(band) too.  ``RepairResult.attempts`` lists every attempt (stage,
cells, moving nodes, seconds, bad cells left).

MPI: the band solve is distributed (PETSc), and so are the neighbourhood
problems (:mod:`nagata_snap.smoothing.neighbourhood`): each process
optimises the part it owns, with the ghost copies of its shared nodes
updated from their owners every iteration (:mod:`nagata_snap.smoothing.untangle`).
Every decision (bad-cell counts, keeping an attempt, the stages, the
bisections) is taken from collective reductions, so all processes take the
same path.  A parallel run takes the serial run's decisions, and its nodes
agree with the serial ones to round-off, except where round-off can decide:
a checked cell within round-off of a threshold of the check (each attempt
records the check's ``margin``), or a kept optimisation that stopped at its
iteration limit (``converged``); ``tests/test_smoothing.py`` compares serial
and parallel runs by these rules.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from typing import Any

import dolfinx.mesh
import mpi4py.MPI
import numpy as np

from nagata_snap.errors import InvertedCellsError
from nagata_snap.mesh.parallel import collective
from nagata_snap.mesh.simplex import (
    cell_columns,
    cells_touching,
    compact_nodes,
    facet_normal_vectors,
    local_facet_vertices,
)
from nagata_snap.smoothing.band import auto_layers, expand, max_layers, prepare
from nagata_snap.smoothing.halo import anywhere, minimum
from nagata_snap.smoothing.kernels import volume_mean_ratio
from nagata_snap.smoothing.neighbourhood import Neighbourhood
from nagata_snap.smoothing.quality import QualityReport, inverted_mask
from nagata_snap.smoothing.slide import SlideFacets, SlidingBoundary
from nagata_snap.smoothing.smooth import Smoother, add_time, smooth_options
from nagata_snap.smoothing.untangle import optimise, targets, volume_ratio_min

__all__ = ["repair", "RepairResult", "InvertedCellsError", "UNTANGLE_LAYERS", "SLIDE_LAYERS",
           "TAPER_LAYERS", "FIRST_SWEEPS", "ELASTIC_NEAR"]

#: Neighbourhood widths (vertex layers around the bad cells) of the untangle
#: attempts; the slide stage reuses the last neighbourhood set up.
UNTANGLE_LAYERS = (3, 6, 12)
#: Largest neighbourhood of a wider untangle attempt: this fraction of the
#: mesh's cells, or this many cells if more.
MAX_REGION_FRACTION = 0.25
MAX_REGION_CELLS = 50_000
#: Snapped boundary vertices within this many layers of a bad cell may slide.
SLIDE_LAYERS = 2
#: Tangent-space / projection rounds of the slide stage.
SLIDE_ROUNDS = 3
#: Blame taper of the partial moves (vertex layers): only the vertices next
#: to the bad cells stay short, with a smooth fraction along the boundary.
TAPER_LAYERS = 2
#: A valid changed cell is *poor* if its mean ratio fell below this fraction
#: of its straight (reference) value: the optimise stage improves it when it
#: can (the check's floor is ``min(min_quality, 0.5 q_ref)``, far below).
POOR_RATIO = 0.7
#: Jacobi sweeps of the first, cheap smoothing over the band (``method='elastic'``).
FIRST_SWEEPS = 8
#: Vertex layers around the bad / poor cells within which moved vertices
#: drive the local elastic solve after the sweeps.
ELASTIC_NEAR = 2
#: Vertex layers around the poor cells whose nodes the optimise stage moves
#: (1: the poor cells' own nodes, 2: and their neighbours'; the 5th
#: percentile of the changed cells' quality needs 2, benchmarks/guard_quality.py).
OPTIMISE_LAYERS = 2
#: Passes of the optimise stage: the first over the poor cells, each later one
#: over the cells that became poor in the pass before.
OPTIMISE_PASSES = 3


@dataclasses.dataclass
class RepairResult:
    """Outcome of :func:`repair` (a valid mesh; identical on all ranks).

    Attributes:
        x: (n, 3) new coordinates of all local geometry nodes.
        fraction: (k,) fraction of its prescribed displacement reached by each
            node of the input ``moved`` (same order); 1 = at the target.
        shortfall: (k,) remaining distance to the target (length unit); 0 for
            nodes that reached it (or slid to another point of the geometry).
        stage: ``'smooth'``, ``'optimise'``, ``'untangle'``, ``'slide'`` or
            ``'partial'`` (``'stiffen'`` with a ``stiffen`` schedule): the
            stage that produced the valid mesh.
        n_inverted_unsmoothed: global number of bad cells with the boundary
            moved and no smoothing.
        n_inverted_smoothed: global number of bad cells after the smooth
            stage (the sweeps, and the elastic solve near the cells they left bad or poor).
        attempts: one dict per attempt: ``stage``, ``layers``, ``cells`` and
            ``nodes`` (global number of cells it worked on and of nodes it
            moved), ``seconds``, ``n_bad`` (bad cells left), ``margin`` (how
            close the checked cells came to a threshold of the check, see
            ``_Guard._margin``: where it is within round-off, a serial and a
            parallel run may decide differently), ``converged`` (stages that
            optimise: see :class:`~nagata_snap.smoothing.untangle.OptimiseResult`),
            ``kept`` (the result was taken), and per stage
            ``method`` / ``exponent`` (smooth), ``slid`` (slide), ``round``,
            ``t`` (partial).
        timings: stage -> seconds on this rank.
        slid: global number of boundary vertices that slid on the geometry.
        report: :class:`QualityReport` of the result (None if not requested).
    """

    x: np.ndarray
    fraction: np.ndarray
    shortfall: np.ndarray
    stage: str
    n_inverted_unsmoothed: int
    n_inverted_smoothed: int
    attempts: list[dict]
    timings: dict[str, float]
    slid: int = 0
    report: QualityReport | None = None

    @property
    def n_shortfall(self) -> int:
        """Local number of moved nodes that did not reach their target."""
        return int(np.count_nonzero(self.shortfall > 0))


class _Guard:
    """What every stage shares: masks, targets, the bad-cell check, the attempt log."""

    def __init__(self, mesh: dolfinx.mesh.Mesh, x_ref: np.ndarray, x_target: np.ndarray,
                 moved: np.ndarray, fixed: np.ndarray, rel_floor: float, min_quality: float,
                 opts: dict[str, Any]):
        self.mesh, self.comm = mesh, mesh.comm
        self.gdim = mesh.geometry.dim
        self.sync, self.x_ref, self.moved_mask, self.fixed_mask = prepare(
            mesh, x_ref, moved, fixed, bool(opts["fix_boundary"]))
        self.x_ref = np.ascontiguousarray(self.x_ref)  # (the compiled check's layout)
        x_target = np.asarray(x_target, dtype=np.float64)
        if x_target.shape != self.x_ref.shape:
            raise ValueError(f"x_target must have shape {self.x_ref.shape}, got {x_target.shape}")
        self.moved_idx = np.asarray(moved, dtype=np.int64).reshape(-1)
        self.x_before = self.sync.forward(x_target)  # owner-consistent copy
        self.x_tgt = self.x_before.copy()  # targets (slid vertices: where they slid to)
        self.cells = mesh.geometry.dofmaps[0]
        self.cols = cell_columns(self.cells)
        self.n_own_cells = mesh.topology.index_map(mesh.topology.dim).size_local
        self.rel_floor, self.min_quality = rel_floor, min_quality
        # cells whose nodes may differ from x_ref: those touching a moved target,
        # plus every band / neighbourhood a stage worked on (see check)
        self.pool = cells_touching(np.any(self.x_tgt != self.x_ref, axis=1), self.cols)
        n = self.cells.shape[0]
        self._v_ref, self._q_floor, self._q_ref = np.empty(n), np.empty(n), np.empty(n)
        self._have_ref = np.zeros(n, dtype=bool)
        # the check's cache: volume and mean ratio of cells at the coordinates _x_at
        # (valid where _have), so a check recomputes only the cells whose nodes moved
        self._vol, self._q = np.empty(n), np.empty(n)
        self._have = np.zeros(n, dtype=bool)
        self._x_at = self.x_ref.copy()
        self._pool_key: np.ndarray | None = None
        self.timings: dict[str, float] = {}
        self.attempts: list[dict] = []
        self.slid = 0
        self.margin = np.inf

    @property
    def disp(self) -> np.ndarray:
        return np.where(self.moved_mask[:, None], self.x_tgt - self.x_ref, 0.0)

    def _ref_data(self, cand: np.ndarray) -> None:
        need = cand[~self._have_ref[cand]]
        if need.size:
            self._v_ref[need], self._q_ref[need] = volume_mean_ratio(self.x_ref, self.cells[need],
                                                                     self.gdim)
            self._q_floor[need] = np.minimum(self.min_quality, 0.5 * self._q_ref[need])
            self._have_ref[need] = True

    def check(self, x: np.ndarray) -> tuple[np.ndarray, int]:
        """Bad local cells ``(nc,)`` (owned and ghost) and their global count (collective).

        A cell is bad if inverted or collapsed w.r.t. ``x_ref`` (relative
        volume floor ``rel_floor``) or below the mean-ratio floor
        ``min(min_quality, 0.5 q_ref)``.  Only pool cells with a node that
        differs from ``x_ref`` are examined: no other cell can have changed.
        Also sets ``poor`` (valid cells below ``POOR_RATIO q_ref``), ``n_poor``
        and ``worst`` (the smallest ``q / q_ref`` over the examined cells,
        global).
        """
        t0 = time.perf_counter()
        if self._pool_key is None or np.any(self._pool_key != self.pool):
            self._pool_key = self.pool.copy()
            pool = np.flatnonzero(self.pool)
            pc = self.cells[pool]
            self._pool = (pool, cell_columns(pc), compact_nodes(pc, self.x_ref.shape[0])[0])
        pool, pcols, nodes = self._pool
        xn = x[nodes]
        changed = np.zeros(x.shape[0], dtype=bool)
        changed[nodes] = np.any(xn != self.x_ref[nodes], axis=1)
        cand = pool[cells_touching(changed, pcols)]
        self._ref_data(cand)
        vol, q = self._measures(x, xn, pool, pcols, nodes, cand)
        badc = inverted_mask(vol, self._v_ref[cand], self.rel_floor)
        if self.min_quality > 0:
            badc |= q < self._q_floor[cand]
        ratio = q / np.maximum(self._q_ref[cand], 1e-300)
        self._margin(vol, q, ratio, cand)
        bad = np.zeros(self.cells.shape[0], dtype=bool)
        bad[cand[badc]] = True
        self.poor = np.zeros_like(bad)
        self.poor[cand[~badc & (ratio < POOR_RATIO)]] = True
        own = slice(0, self.n_own_cells)
        nbad, self.n_poor = self.comm.allreduce(
            np.array([np.count_nonzero(bad[own]), np.count_nonzero(self.poor[own])]))
        own_c = cand < self.n_own_cells
        self.worst = self.comm.allreduce(float(ratio[own_c].min(initial=1.0)), op=mpi4py.MPI.MIN)
        add_time(self.timings, "check", time.perf_counter() - t0)
        return bad, int(nbad)

    def _margin(self, vol: np.ndarray, q: np.ndarray, ratio: np.ndarray, cand: np.ndarray) -> None:
        """``margin``: how close the examined cells ``cand`` are to a threshold of the check (collective).

        The smallest of ``|vol / |v_ref| - rel_floor|`` (volume ratio against
        the inversion floor), ``|q - q_floor| / q_ref`` (mean ratio against its
        floor) and ``|q / q_ref - POOR_RATIO|`` over the owned examined cells, all
        relative to the straight cell, over all processes.  A count of bad or
        poor cells, and every decision taken from it, can differ between two
        runs whose coordinates differ by round-off only if the margin is
        within that round-off's effect (``RepairResult.attempts`` record it).
        """
        own = cand < self.n_own_cells
        v_ref, q_ref = self._v_ref[cand[own]], np.maximum(self._q_ref[cand[own]], 1e-300)
        m = np.abs(vol[own] * np.sign(v_ref) / np.maximum(np.abs(v_ref), 1e-300) - self.rel_floor)
        if self.min_quality > 0:
            m = np.minimum(m, np.abs(q[own] - self._q_floor[cand[own]]) / q_ref)
        m = np.minimum(m, np.abs(ratio[own] - POOR_RATIO))
        self.margin = float(self.comm.allreduce(float(m.min(initial=np.inf)), op=mpi4py.MPI.MIN))

    def _measures(self, x: np.ndarray, xn: np.ndarray, pool: np.ndarray, pcols: list[np.ndarray],
                  nodes: np.ndarray, cand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed volumes and mean ratios ``(k,)`` of the cells ``cand`` at ``x`` (the check's cache).

        Only cells with a node whose coordinates differ from those of the
        cached value (or without one) are computed (compiled kernel); ``xn``
        is ``x[nodes]``, the pool's nodes.
        """
        moved = np.zeros(x.shape[0], dtype=bool)
        moved[nodes] = np.any(xn != self._x_at[nodes], axis=1)
        self._have[pool[cells_touching(moved, pcols)]] = False
        self._x_at[nodes] = xn
        need = cand[~self._have[cand]]
        if need.size:
            self._vol[need], self._q[need] = volume_mean_ratio(
                np.ascontiguousarray(x, dtype=np.float64), self.cells[need], self.gdim)
            self._have[need] = True
        return self._vol[cand], self._q[cand]

    def state(self) -> tuple[np.ndarray, int, float]:
        """What :meth:`check` sets besides its result: ``(poor, n_poor, worst)``."""
        return self.poor, self.n_poor, self.worst

    def restore(self, state: tuple[np.ndarray, int, float]) -> None:
        """Set ``poor, n_poor, worst`` back to those of an earlier :meth:`state`."""
        self.poor, self.n_poor, self.worst = state

    def log(self, stage: str, t0: float, n_bad: int, **info: Any) -> None:
        """Record one attempt (``seconds``: wall time since ``t0``, max over processes)."""
        dt = self.comm.allreduce(time.perf_counter() - t0, op=mpi4py.MPI.MAX)
        self.attempts.append({"stage": stage, **info, "seconds": dt, "n_bad": n_bad,
                              "margin": self.margin})

    def positions(self, alpha: np.ndarray) -> np.ndarray:
        """Targets with the moved nodes at fractions ``alpha (n,)`` of their displacement."""
        x = self.x_tgt.copy()
        part = self.moved_mask & (alpha < 1.0)
        x[part] = self.x_ref[part] + alpha[part, None] * (self.x_tgt[part] - self.x_ref[part])
        return x


# ---------------------------------------------------------------------------
# Stages
# ---------------------------------------------------------------------------


def _linear(g: _Guard, method: str, o: dict[str, Any], stiffen: tuple[tuple[float, int], ...],
            first_sweeps: int | None = None
            ) -> tuple[np.ndarray, np.ndarray, int, Smoother]:
    """Stage ``smooth``: the band smoother (then the optional ``stiffen`` schedule).

    With ``method='elastic'`` and ``first_sweeps``: the sweeps over the band
    first, the elastic solve only near the bad or poor cells they leave
    (:func:`_elastic_near`).  Returns ``(x, bad, nbad, smoother)``, the
    smoother over the whole band (the partial stage re-solves it).
    """
    first: list[tuple[str, dict[str, Any]]] = [(method, o)]
    if method == "elastic" and first_sweeps:
        first = [("laplace", dict(o, sweeps=int(first_sweeps)))]
    schedule = first + [("elastic", dict(o, exponent=o["exponent"] + dp,
                                         layers=np.asarray(o["layers"]) * int(mult)))
                        for dp, mult in stiffen]
    sm = None
    for k, (meth, oo) in enumerate(schedule):
        t0 = time.perf_counter()
        if sm is not None:
            sm.destroy()
        sm = Smoother(g.mesh, g.x_ref, g.moved_mask, g.fixed_mask, g.sync, meth, oo, g.timings)
        x = sm.run(g.x_tgt)
        g.pool[sm.cells] = True
        bad, nbad = g.check(x)
        band = sm.band
        extra = {"sweeps": int(oo["sweeps"])} if meth == "laplace" and oo["sweeps"] else {}
        g.log("smooth" if k == 0 else "stiffen", t0, nbad, method=meth, exponent=oo["exponent"],
              layers=max_layers(oo["layers"], g.comm), cells=band.n_cells_global if band else 0,
              nodes=band.n_free_global if band else 0, **extra)
        if k == 0 and meth != method and nbad:
            x, bad, nbad = _elastic_near(g, x, bad, nbad, o)
        if nbad == 0:
            break
    assert sm is not None  # the schedule has at least the first smoother
    return x, bad, nbad, sm


def _elastic_near(g: _Guard, x: np.ndarray, bad: np.ndarray, nbad: int, o: dict[str, Any]
                  ) -> tuple[np.ndarray, np.ndarray, int]:
    """The elastic band smoother driven by the moved vertices near the bad / poor cells only.

    The moved vertices within :data:`ELASTIC_NEAR` layers of the bad or poor
    cells prescribe their displacement; the other moved vertices, and the
    outer layer of the band, keep their coordinates in ``x`` (the swept
    mesh).  Kept if it leaves no more bad cells and, without bad cells, does
    not lower the worst quality ratio.
    """
    t0 = time.perf_counter()
    mark = np.zeros(g.sync.n, dtype=bool)
    mark[g.cells[bad].reshape(-1)] = True
    near, _, _ = expand(g.cells, g.sync.any(mark), ELASTIC_NEAR, g.sync)
    moved = g.moved_mask & near
    fixed = g.fixed_mask | (g.moved_mask & ~near)
    worst, before = g.worst, g.state()
    sm = Smoother(g.mesh, g.x_ref, moved, fixed, g.sync, "elastic", o, g.timings)
    try:
        xn = sm.run(x)
    finally:
        sm.destroy()
    g.pool[sm.cells] = True
    bn, nb = g.check(xn)
    band = sm.band
    keep = nb < nbad or (nb == nbad and (nb > 0 or g.worst >= worst))
    g.log("smooth", t0, nb, method="elastic", exponent=o["exponent"],
          layers=max_layers(o["layers"], g.comm), cells=band.n_cells_global if band else 0,
          nodes=band.n_free_global if band else 0, kept=keep)
    if keep:
        return xn, bn, nb
    g.restore(before)  # (poor, n_poor and worst of x)
    return x, bad, nbad


class _Local:
    """A neighbourhood with what the optimiser needs (set up once, reused; collective)."""

    def __init__(self, g: _Guard, bad: np.ndarray, layers: int):
        self.nbh = Neighbourhood(g.mesh, g.sync, bad, layers, g.x_ref)
        self.layers = layers
        self.winv = collective(g.comm, targets, g.x_ref[:, : g.gdim], self.nbh.cells)
        self.constrained = g.moved_mask | g.fixed_mask | ~self.nbh.complete
        g.pool[self.nbh.local_cells] = True

    def seeds(self, g: _Guard, bad: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: the neighbourhood's nodes of the bad cells of any process (collective)."""
        return self.nbh.any(_cell_nodes(g, bad))

    def distance(self, g: _Guard, bad: np.ndarray) -> np.ndarray:
        """Vertex-layer distance ``(n,)`` of the local nodes from the bad cells (collective)."""
        return self.nbh.distance(self.seeds(g, bad))

    def run(self, g: _Guard, x: np.ndarray, free: np.ndarray, **kw) -> tuple[np.ndarray, Any]:
        """Optimise the nodes ``free (n,)`` from ``x (n, 3)`` (collective); new local coordinates."""
        d = g.gdim
        res = optimise(x[:, :d], self.nbh.cells, self.winv, free, self.nbh.scale,
                       layout=self.nbh.layout, **kw)
        xn = x.copy()
        xn[:, :d] = res.x
        return xn, res

    def reach(self, g: _Guard, bad: np.ndarray, dist: np.ndarray) -> int:
        """Largest ``dist`` (e.g. from the seeds) on the nodes of the bad cells (collective)."""
        return self.nbh.reach(_cell_nodes(g, bad), dist)

    def cells_moving(self, moving: np.ndarray) -> int:
        return self.nbh.cells_moving(moving)


def _count(g: _Guard, nodes: np.ndarray) -> int:
    """Global number of the nodes ``nodes (n,)`` (bool; counted by their owners; collective)."""
    return int(g.comm.allreduce(int(np.count_nonzero(nodes[: g.sync.n_owned]))))


def _cell_nodes(g: _Guard, cells: np.ndarray) -> np.ndarray:
    """``(n,)`` bool: the nodes of the local cells ``cells (nc,)`` (bool)."""
    mark = np.zeros(g.sync.n, dtype=bool)
    mark[g.cells[cells].reshape(-1)] = True
    return mark


def _optimise(g: _Guard, x: np.ndarray) -> tuple[np.ndarray, bool]:
    """Stage ``optimise``: the mesh is valid but some changed cells are poor; improve them.

    An active set that shrinks: the first pass moves the nodes within
    :data:`OPTIMISE_LAYERS` of the poor cells, each later one (at most
    :data:`OPTIMISE_PASSES` in all) only around the cells that became poor
    since (a pass leaves the cells it worked on at a minimum of the
    objective: optimising them again would not move them).  A pass is kept
    if it leaves no bad cell, no lower worst quality ratio ``q / q_ref`` and
    no more poor cells, and improves one of the two.  Returns ``(x, kept)``:
    ``kept`` if any pass was.
    """
    t_stage = time.perf_counter()
    kept_any = False
    done = np.zeros_like(g.poor)
    seeds = g.poor
    for _ in range(OPTIMISE_PASSES):
        t0 = time.perf_counter()
        before = g.state()
        worst, n_poor = before[2], before[1]
        loc = _Local(g, seeds, OPTIMISE_LAYERS)  # (its nodes within OPTIMISE_LAYERS - 1 are complete)
        free = (loc.distance(g, seeds) < OPTIMISE_LAYERS) & ~loc.constrained
        xn, res = loc.run(g, x, free, shrink=True)
        _, nb = g.check(xn)
        keep = (nb == 0 and g.worst >= worst and g.n_poor <= n_poor
                and (g.worst > worst or g.n_poor < n_poor))
        g.log("optimise", t0, nb, layers=OPTIMISE_LAYERS, cells=loc.cells_moving(free),
              nodes=_count(g, free), worst=g.worst, poor=int(g.n_poor), kept=bool(keep),
              converged=res.converged)
        if not keep:
            g.restore(before)  # (poor, n_poor and worst of x)
            break
        x, kept_any = xn, True
        done |= seeds
        seeds = g.poor & ~done  # the cells that became poor in this pass
        if not g.comm.allreduce(bool(seeds[: g.n_own_cells].any()), op=mpi4py.MPI.LOR):
            break
    add_time(g.timings, "optimise", time.perf_counter() - t_stage)
    return x, kept_any


def _pinned(g: _Guard, x: np.ndarray, bad: np.ndarray) -> int:
    """Global number of bad cells that no interior motion can repair (collective).

    Such a cell has only constrained vertices, or a facet of constrained
    vertices that turned over (its normal reversed against the straight
    mesh): the snapped boundary itself folded there.
    """
    cells = g.cells[np.flatnonzero(bad[: g.n_own_cells])]
    con = g.moved_mask | g.fixed_mask
    pinned = con[cells].all(axis=1)
    lf = local_facet_vertices(g.mesh.topology.dim)
    for f in lf:  # the d + 1 facets of each cell
        fn = cells[:, f]
        turned = np.einsum("ij,ij->i", facet_normal_vectors(x[fn]),
                           facet_normal_vectors(g.x_ref[fn])) < 0
        pinned |= con[fn].all(axis=1) & turned
    return g.comm.allreduce(int(np.count_nonzero(pinned)))


def _untangle(g: _Guard, x: np.ndarray, bad: np.ndarray, nbad: int, can_slide: bool
              ) -> tuple[np.ndarray, np.ndarray, int, _Local]:
    """Stage ``untangle``: optimise the interior nodes near the bad cells, wider and wider.

    Each attempt keeps its result if it leaves no more bad cells than before;
    the neighbourhood is reused while it is wide enough.  A wider
    attempt follows if the last one lowered the count of bad cells or if the
    cells still bad reach the edge of its moving region (the trouble needs
    room); otherwise, with ``can_slide``, more interior nodes will not help
    and the slide stage is next.  No wider attempt takes more than
    :data:`MAX_REGION_FRACTION` of the mesh (or :data:`MAX_REGION_CELLS`).
    """
    t_stage = time.perf_counter()
    loc = None
    n_mesh = g.mesh.topology.index_map(g.mesh.topology.dim).size_global
    for k, layers in enumerate(UNTANGLE_LAYERS):
        t0 = time.perf_counter()
        seeds = bad  # (the poor cells are the optimise stage's, after the untangling)
        if loc is None or loc.layers <= layers:
            wider = _Local(g, seeds, layers + 1)
            if k and wider.nbh.n_cells > max(MAX_REGION_FRACTION * n_mesh, MAX_REGION_CELLS):
                break
            loc = wider
        dist = loc.distance(g, seeds)
        free = (dist < layers) & ~loc.constrained
        xn, res = loc.run(g, x, free)
        bn, nb = g.check(xn)
        g.log("untangle", t0, nb, layers=layers, cells=loc.cells_moving(free),
              nodes=_count(g, free), kept=nb <= nbad, converged=res.converged)
        progress = nb < nbad
        if nb <= nbad:  # keep an improvement (or an equal count: better shapes)
            x, bad, nbad = xn, bn, nb
        if nbad == 0:
            break
        if can_slide and not progress and loc.reach(g, bn, dist) < layers - 1:
            break  # pinned by the boundary: sliding is the next step
    add_time(g.timings, "untangle", time.perf_counter() - t_stage)
    assert loc is not None  # the first attempt always sets up its neighbourhood
    return x, bad, nbad, loc


def _slide(g: _Guard, x: np.ndarray, bad: np.ndarray, nbad: int, loc: _Local,
           boundary: SlidingBoundary) -> tuple[np.ndarray, np.ndarray, int]:
    """Stage ``slide``: snapped boundary vertices near the bad cells move on the geometry too."""
    t0 = time.perf_counter()
    d = g.gdim
    nbh = loc.nbh
    dist = loc.distance(g, bad)
    sl = boundary.eligible(g.sync) & nbh.complete & (dist <= SLIDE_LAYERS)
    free = (dist < UNTANGLE_LAYERS[0]) & ~loc.constrained & ~sl
    facets = SlideFacets(boundary, nbh, sl, g.x_ref, x) if anywhere(g.comm, bool(sl.any())) else None
    if facets is not None and anywhere(g.comm, bool(facets.corner.any())):  # corners stay (alike on every copy)
        sl[facets.slide[facets.corner]] = False
        facets = SlideFacets(boundary, nbh, sl, g.x_ref, x) if anywhere(g.comm, bool(sl.any())) else None
    if facets is None:
        g.log("slide", t0, nbad, layers=loc.layers - 1, cells=0, nodes=0, slid=0)
        return x, bad, nbad
    si = facets.slide
    xc = x[:, :d].copy()
    x0 = xc[si].copy()
    best, converged = -np.inf, True
    for _ in range(SLIDE_ROUNDS):
        p, basis = facets.tangents(xc, nbh.scale)
        xc[si] = p
        res = optimise(xc, nbh.cells, loc.winv, free, nbh.scale, slide=si, basis=basis,
                       layout=nbh.layout)
        xc, converged = res.x, converged and res.converged
        xc[si] = facets.project(xc, xc[si])
        smin = minimum(g.comm, volume_ratio_min(xc, nbh.cells, loc.winv))
        if smin <= best:
            break  # sliding no longer helps
        best = smin
        if smin > 0:
            break
    slid = np.any(xc[si] != x0, axis=1)
    xn = x.copy()
    xn[:, :d] = xc
    bn, nb = g.check(xn)
    moving = free | sl
    n_slid = int(g.comm.allreduce(int(np.count_nonzero(slid[si < g.sync.n_owned]))))
    g.log("slide", t0, nb, layers=loc.layers - 1, cells=loc.cells_moving(moving),
          nodes=_count(g, moving), slid=n_slid, kept=nb <= nbad, converged=converged)
    add_time(g.timings, "slide", g.attempts[-1]["seconds"])
    if nb > nbad:
        return x, bad, nbad
    facets.commit(slid)
    g.slid += n_slid
    # slid vertices: at their new target (on the geometry), now "moved"
    g.x_tgt[si[slid]] = xn[si[slid]]
    g.moved_mask[si[slid]] = True
    return xn, bn, nb


def _blame(dist: np.ndarray, moved: np.ndarray, radius: int, taper: int) -> np.ndarray:
    """Blame weights ``(N,)``: 1 within ``radius`` layers, linear to 0 over ``taper`` more."""
    w = np.clip(1.0 - (dist - radius) / (taper + 1.0), 0.0, 1.0)
    return np.where(moved, w, 0.0)


_TrialResult = tuple[np.ndarray, np.ndarray, np.ndarray, int]


def _partial_trial(g: _Guard, loc: _Local, free: np.ndarray, alpha: np.ndarray, w_loc: np.ndarray,
                   base_x: np.ndarray, fmin: float, rnd: int, t: float) -> _TrialResult:
    """One trial of a partial round: blamed vertices (weights ``w_loc (n,)``) at ``t`` of the way (collective).

    The fractions are ``alpha - (1 - t) w (alpha - fmin)``; the neighbourhood
    ``loc`` is re-optimised (its ``free`` nodes) from ``base_x`` with the
    moved nodes there.  Returns ``(x, alpha_t (n,), bad (nc,), nbad)``.
    """
    t0 = time.perf_counter()
    a_t = alpha - (1.0 - t) * w_loc * (alpha - fmin)
    xt = np.where(g.moved_mask[:, None], g.positions(a_t), base_x)
    xn, res = loc.run(g, xt, free)
    bn, nb = g.check(xn)
    g.log("partial", t0, nb, round=rnd, t=t, layers=loc.layers,
          cells=loc.cells_moving(free), nodes=_count(g, free), converged=res.converged)
    return xn, a_t, bn, nb


def _bisect(trial: Callable[[float], _TrialResult], steps: int) -> _TrialResult:
    """The valid trial of the largest ``t`` found by ``steps`` bisection steps on ``(0, 1)``.

    Without a valid trial, the trial at ``t = 0`` (which may still leave bad cells).
    """
    good, t_lo, t_hi = None, 0.0, 1.0  # good: (x, alpha, bad, nbad) of the best valid trial
    for _ in range(steps):
        t = 0.5 * (t_lo + t_hi)
        out = trial(t)
        if out[3] == 0:
            t_lo, good = t, out
        else:
            t_hi = t
    return trial(0.0) if good is None else good


def _partial(g: _Guard, x: np.ndarray, bad: np.ndarray, nbad: int, sm: Smoother,
             min_fraction: float, bisection_steps: int, implicate_layers: int,
             max_rounds: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Stage ``partial``: the blamed moved vertices only part of the way (see module docstring).

    Returns ``(x, alpha (n,), bad, nbad)``.
    """
    fmin = float(min_fraction)
    alpha = np.ones(g.sync.n)
    base_x = x
    for rnd in range(int(max_rounds)):
        radius = max(1, int(implicate_layers)) * 2**rnd
        loc = _Local(g, bad, radius + TAPER_LAYERS + 3)
        nbh = loc.nbh
        dist = loc.distance(g, bad)
        w_loc = _blame(dist, g.moved_mask & nbh.nodes, radius, TAPER_LAYERS) * (alpha > fmin)
        free = ~loc.constrained & (dist <= radius + TAPER_LAYERS + 2)
        good = _bisect(functools.partial(_partial_trial, g, loc, free, alpha, w_loc, base_x, fmin, rnd),
                       int(bisection_steps))
        if good[3] == 0:
            return good[0], good[1], good[2], 0
        if good[3] >= nbad:
            break  # even the blamed vertices at min_fraction do not help: no wider round will
        base_x, alpha, bad, nbad = good
    # final round: every moved vertex blamed, the band smoother re-solved
    t0 = time.perf_counter()
    alpha = np.where(g.moved_mask, np.minimum(alpha, fmin), 1.0)
    xn = sm.run(g.positions(alpha))
    bad, nbad = g.check(xn)
    band = sm.band
    g.log("partial", t0, nbad, round=int(max_rounds), t=0.0, layers=0,
          cells=band.n_cells_global if band else 0, nodes=band.n_free_global if band else 0)
    return xn, alpha, bad, nbad


def _fail(g: _Guard, bad: np.ndarray, why: str) -> None:
    """Raise :class:`InvertedCellsError` naming the bad cells (global indices, all processes)."""
    cim = g.mesh.topology.index_map(g.mesh.topology.dim)
    own_bad = np.flatnonzero(bad[: g.n_own_cells]).astype(np.int32)
    gbad = cim.local_to_global(own_bad) if own_bad.size else np.zeros(0, dtype=np.int64)
    allbad = np.sort(np.concatenate(g.comm.allgather(np.asarray(gbad, dtype=np.int64))))
    first = ", ".join(str(c) for c in allbad[:10])
    more = " ..." if allbad.size > 10 else ""
    raise InvertedCellsError(
        f"{allbad.size} cell(s) inverted or below the quality floor after smoothing "
        f"and repair ({why}); global cell indices: [{first}{more}]",
        cells=allbad[:100], count=allbad.size)


def _result(g: _Guard, x: np.ndarray, alpha: np.ndarray, stage: str, n_unsmoothed: int,
            report: bool | str, t_start: float) -> RepairResult:
    """The :class:`RepairResult` (and its quality report) of a valid ``x``."""
    disp = np.linalg.norm(g.disp, axis=1)
    short_all = np.where(g.moved_mask, (1.0 - alpha) * disp, 0.0)
    idx = g.moved_idx
    g.timings["total"] = time.perf_counter() - t_start
    rep = None
    if report:
        t0 = time.perf_counter()
        scope = "changed" if report is True else str(report)
        own_moved = np.flatnonzero(g.moved_mask[: g.sync.n_owned])
        rep = QualityReport.from_mesh(g.mesh, x, x_ref=g.x_ref, x_before=g.x_before,
                                      rel_floor=g.rel_floor, timings=dict(g.timings),
                                      shortfall=short_all[own_moved], scope=scope)
        g.timings["report"] = time.perf_counter() - t0
        rep.timings["report"] = g.comm.allreduce(g.timings["report"], op=mpi4py.MPI.MAX)
    smoothed = [a["n_bad"] for a in g.attempts if a["stage"] == "smooth" and a.get("kept", True)]
    n_smoothed = smoothed[-1] if smoothed else 0
    return RepairResult(x=x, fraction=np.asarray(alpha[idx] if idx.size else np.zeros(0)),
                        shortfall=np.asarray(short_all[idx] if idx.size else np.zeros(0)),
                        stage=stage, n_inverted_unsmoothed=n_unsmoothed,
                        n_inverted_smoothed=n_smoothed, attempts=g.attempts,
                        timings=g.timings, slid=g.slid, report=rep)


# ---------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------


def repair(mesh: dolfinx.mesh.Mesh, x_ref: np.ndarray, x_target: np.ndarray, moved: np.ndarray,
           fixed: np.ndarray, method: str = "elastic", *,
           rel_floor: float = 1e-12, min_quality: float = 0.01,
           untangle: bool = True, slide: SlidingBoundary | None = None,
           stiffen: tuple[tuple[float, int], ...] = (),
           allow_partial: bool = True, min_fraction: float = 0.0,
           bisection_steps: int = 6, implicate_layers: int = 1, max_rounds: int = 5,
           report: bool | str = True, first_sweeps: int | None = FIRST_SWEEPS,
           **opts) -> RepairResult:
    """Smooth, guard against inverted / degenerate cells, repair or fail.

    Collective on ``mesh.comm``. Neither ``mesh`` nor any input array is
    modified (``slide.records`` is updated when vertices slid); the caller
    writes ``result.x`` into its mesh on success.  The stages are described
    in the module docstring.

    Args:
        mesh: P1 simplex ``dolfinx.mesh.Mesh`` (topology / parallel layout;
            its coordinates are only checked to be finite).
        x_ref: (n, 3) straight reference coordinates (all local nodes).
        x_target: (n, 3) coordinates with the moved nodes at their targets;
            its other rows (fixed nodes, nodes outside the band) are kept.
        moved, fixed: (k,), (m,) int32 local geometry-node indices, as in
            :func:`~nagata_snap.smoothing.smooth.smooth`.
        method: first smoother, ``'elastic'``, ``'laplace'`` or ``'none'``.
        rel_floor: relative volume floor for inversion.
        min_quality: mean-ratio floor in [0, 1] (0 disables the quality
            guard; 1 = equilateral); a cell is bad below
            ``min(min_quality, 0.5 q_ref)``.
        untangle: run the untangle (and slide) stages.
        slide: the snapped facets whose vertices may slide
            (:class:`~nagata_snap.smoothing.slide.SlidingBoundary`); None: no sliding.
        stiffen: optional band-wide re-solves after the first smoother, each
            ``(exponent increment, band multiplier)`` (the repair before the
            untangler; kept for comparisons, default none).
        allow_partial: allow partial moves; if False, that stage is skipped.
        min_fraction: smallest acceptable displacement fraction per node.
        bisection_steps: bisection steps on ``t`` per partial round.
        implicate_layers: moved nodes within this many layers of a bad cell
            get the full blame in the first partial round (twice as many each round).
        max_rounds: partial rounds before the final, global one.
        report: build a :class:`QualityReport`: ``True`` or ``"changed"``
            (metrics over the cells snapping / smoothing changed, O(band)),
            ``"all"`` (every cell, O(mesh)) or ``False`` (none).
        first_sweeps: with ``method='elastic'``, Jacobi sweeps over the band
            before the elastic solve, which then runs only near the cells
            still bad or poor (stage ``smooth`` above); 0 or None: the
            elastic solve over the whole band.
        **opts: smoothing options of :func:`~nagata_snap.smoothing.smooth.smooth`
            (``layers``, ``exponent``, ...).

    Returns:
        :class:`RepairResult`.

    Raises:
        InvertedCellsError: no valid mesh within the constraints.
    """
    t_start = time.perf_counter()
    o = smooth_options(opts)
    g = _Guard(mesh, x_ref, x_target, moved, fixed, rel_floor, min_quality, o)
    if o["layers"] == "auto":
        o["layers"] = auto_layers(g.x_ref, g.disp, g.cells, g.pool, g.sync)
    _, n_unsmoothed = g.check(g.x_tgt)
    x, bad, nbad, sm = _linear(g, method, o, stiffen, first_sweeps)
    stage = "stiffen" if any(a["stage"] == "stiffen" for a in g.attempts) else "smooth"
    alpha = np.ones(g.sync.n)
    try:
        if nbad and untangle:
            # interior motion first, unless some bad cells need the boundary to move
            if slide is None or _pinned(g, x, bad) == 0:
                x, bad, nbad, loc = _untangle(g, x, bad, nbad, slide is not None)
                stage = "untangle"
            else:
                loc = _Local(g, bad, UNTANGLE_LAYERS[1] + 1)
            if nbad and slide is not None:
                x, bad, nbad = _slide(g, x, bad, nbad, loc, slide)
                stage = "slide"
        if nbad == 0 and untangle and g.n_poor and method != "none":
            x, kept = _optimise(g, x)
            stage = "optimise" if kept and stage == "smooth" else stage
        if nbad and allow_partial:
            x, alpha, bad, nbad = _partial(g, x, bad, nbad, sm, min_fraction, bisection_steps,
                                           implicate_layers, max_rounds)
            stage = "partial"
    finally:
        sm.destroy()
    if nbad:
        _fail(g, bad, "partial moves disabled" if not allow_partial else
              f"even with every implicated node moved only {min_fraction:g} of the way")
    return _result(g, x, alpha, stage, n_unsmoothed, report, t_start)
