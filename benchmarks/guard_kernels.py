"""Microseconds per tetrahedron of the guard's kernels: numpy against the compiled (numba) ones.

On a perturbed structured tetrahedral mesh (``--n`` cubes per side, 6 tets
each; some cells inverted) it times, best of ``--repeat``:

* energy + gradient + cell Hessians of the untangling objective
  (:func:`~nagata_snap.smoothing.untangle.energy_numpy` against
  :func:`~nagata_snap.smoothing.untangle.energy`);
* energy only (the line search);
* the check's signed volumes + mean ratios (``signed_volumes`` +
  ``mean_ratio`` against :func:`~nagata_snap.smoothing.kernels.volume_mean_ratio`);
* the band matrix blocks summed per node pair (argsort + ``_summed_blocks``
  against :func:`~nagata_snap.smoothing.kernels.band_blocks`);
* the optimiser's evaluation, the cell Hessians added into the Newton matrix
  blocks: :func:`~nagata_snap.smoothing.kernels.energy_terms` then
  :func:`~nagata_snap.smoothing.kernels.sum_hessians` against the fused
  :func:`~nagata_snap.smoothing.kernels.energy_blocks`.

It also prints the first call's time in this process (import of the
cached machine code, or its compilation on a machine without the cache:
run it twice to see both).  Last line: ``guard_kernel_us_per_tet <compiled
energy + gradient + Hessian>``.

    python benchmarks/guard_kernels.py [--n 30] [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import mpi4py.MPI as MPI
import numpy as np

sys.path[:0] = [os.path.dirname(os.path.dirname(os.path.abspath(__file__)))]

import dolfinx.mesh  # noqa: E402


def best(fn, repeat: int) -> float:
    out = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out = min(out, time.perf_counter() - t)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=30)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    t0 = time.perf_counter()
    from nagata_snap.smoothing import kernels
    from nagata_snap.smoothing.untangle import _Cells, energy, energy_numpy, targets
    t_import = time.perf_counter() - t0

    from nagata_snap.mesh.simplex import p1_gradients, signed_volumes
    from nagata_snap.smoothing.quality import mean_ratio
    from nagata_snap.smoothing.smooth import _lame, _summed_blocks

    m = dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, args.n, args.n, args.n)
    x = np.array(m.geometry.x)
    cells = np.array(m.geometry.dofmaps[0], dtype=np.int64)
    nc = cells.shape[0]
    winv = targets(x, cells)
    rng = np.random.default_rng(1)
    xp = x + 0.25 / args.n * rng.standard_normal(x.shape)
    prep = _Cells(cells, winv, x.shape[0])
    t0 = time.perf_counter()
    energy(xp[:40], cells[:10], winv[:10], 1e-3, hessian=True)
    energy(xp[:40], cells[:10], winv[:10], 1e-3, grad=False)
    kernels.volume_mean_ratio(xp, cells[:10], 3)
    t_first = time.perf_counter() - t0
    us = 1e6 / nc
    rows = []
    t_np = best(lambda: energy_numpy(xp, None, None, 1e-3, prepared=prep, hessian=True), args.repeat)
    t_nb = best(lambda: energy(xp, None, None, 1e-3, prepared=prep, hessian=True), args.repeat)
    rows.append(("energy + gradient + Hessian", t_np, t_nb))
    rows.append(("energy only",
                 best(lambda: energy_numpy(xp, None, None, 1e-3, grad=False, prepared=prep), args.repeat),
                 best(lambda: energy(xp, None, None, 1e-3, grad=False, prepared=prep), args.repeat)))
    rows.append(("volume + mean ratio (check)",
                 best(lambda: (signed_volumes(xp, cells, 3), mean_ratio(xp, cells, 3)), args.repeat),
                 best(lambda: kernels.volume_mean_ratio(xp, cells, 3), args.repeat)))
    G, meas = p1_gradients(x, cells, 3)
    w = meas * (meas.max() / meas)
    gid = cells.copy()
    nf = x.shape[0]
    mu, lmbda = _lame(0.3)

    def numpy_blocks() -> None:
        c, a, b = np.nonzero(np.ones((nc, 4, 4), dtype=bool))
        key = gid[c, a] * nf + gid[c, b]
        order = np.argsort(key)
        key = key[order]
        start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        _summed_blocks(G, w, "elastic", 0.3, c[order], a[order], b[order], start)

    rows.append(("band matrix blocks (elastic)", best(numpy_blocks, args.repeat),
                 best(lambda: kernels.band_blocks(G, w, gid, gid, 0, mu, lmbda, nf, nf), args.repeat)))
    print(f"{nc} tets; import of the kernels {t_import:.2f} s, first calls {t_first:.2f} s")
    print(f"{'kernel':32s} {'numpy us/tet':>13s} {'compiled us/tet':>16s} {'speed-up':>9s}")
    for name, a, b in rows:
        print(f"{name:32s} {a * us:13.3f} {b * us:16.3f} {a / b:9.1f}")
    # the optimiser's evaluation: the cell Hessians added into the Newton matrix blocks
    # (every node moving), as two passes with the (m, 4, 3, 4, 3) array between them or fused
    B, sv = prep.B, np.ones(cells.shape)
    slot, brow, _ = kernels.hessian_blocks(cells, x.shape[0])
    kernels.energy_blocks(xp, cells, B, 1e-3, sv, slot, brow.size)
    t_two = best(lambda: kernels.sum_hessians(kernels.energy_terms(xp, cells, B, 1e-3, True, sv)[3],
                                              slot, brow.size), args.repeat)
    t_one = best(lambda: kernels.energy_blocks(xp, cells, B, 1e-3, sv, slot, brow.size), args.repeat)
    print(f"energy + gradient + Hessian into the matrix blocks: cell Hessians then sum_hessians "
          f"{t_two * us:.3f} us/tet, fused (energy_blocks) {t_one * us:.3f} us/tet")
    print(f"guard_kernel_us_per_tet {t_nb * us:.3f}")


if __name__ == "__main__":
    main()
