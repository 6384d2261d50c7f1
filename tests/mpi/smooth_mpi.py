"""MPI consistency check for nagata_snap.smoothing.smooth (run under mpiexec).

For each ghost mode, the same boundary displacement is applied to a
distributed unit-square mesh and to a serial copy (COMM_SELF) on every rank;
the owned coordinates of the distributed result are gathered on rank 0 and
compared with the serial result by original input index
(``geometry.input_global_indices``). Rank 0 prints one JSON line per case:
``{"case": ..., "maxdiff": ..., "n": ..., ...}`` and finally ``DONE``.
"""

import json
import os
import sys

import mpi4py.MPI as MPI
import numpy as np

import dolfinx
import dolfinx.mesh

from nagata_snap.smoothing.quality import inverted_cells
from nagata_snap.smoothing.repair import repair
from nagata_snap.smoothing.smooth import smooth

N = 16
H = 1.0 / N
TOL = 1e-12


def setup(comm, ghost_mode, amp):
    msh = dolfinx.mesh.create_unit_square(comm, N, N, ghost_mode=ghost_mode)
    x_ref = msh.geometry.x.copy()
    x = x_ref
    left = np.flatnonzero((x[:, 0] < TOL) & (x[:, 1] > TOL) & (x[:, 1] < 1 - TOL))
    bnd = np.flatnonzero((x[:, 0] < TOL) | (x[:, 0] > 1 - TOL)
                         | (x[:, 1] < TOL) | (x[:, 1] > 1 - TOL))
    fixed = np.setdiff1d(bnd, left).astype(np.int32)
    left = left.astype(np.int32)
    msh.geometry.x[left, 0] += amp * np.sin(np.pi * x_ref[left, 1])
    return msh, x_ref, left, fixed


def setup_refined(comm, amp):
    """Refined (twice, in parallel) unit square; compared by coordinates."""
    msh = dolfinx.mesh.create_unit_square(comm, 8, 8)
    for _ in range(2):
        msh.topology.create_entities(1)
        msh, _, _ = dolfinx.mesh.refine(msh)
    x_ref = msh.geometry.x.copy()
    x = x_ref
    left = np.flatnonzero((x[:, 0] < TOL) & (x[:, 1] > TOL) & (x[:, 1] < 1 - TOL))
    bnd = np.flatnonzero((x[:, 0] < TOL) | (x[:, 0] > 1 - TOL)
                         | (x[:, 1] < TOL) | (x[:, 1] > 1 - TOL))
    fixed = np.setdiff1d(bnd, left).astype(np.int32)
    left = left.astype(np.int32)
    msh.geometry.x[left, 0] += amp * np.sin(np.pi * x_ref[left, 1])
    return msh, x_ref, left, fixed


def by_coords(x_ref, x):
    """Rows of x sorted by the reference coordinates (unique per node)."""
    order = np.lexsort((x_ref[:, 1], x_ref[:, 0]))
    return x_ref[order], x[order]


def owned(msh, x):
    n = msh.geometry.index_map().size_local
    return msh.geometry.input_global_indices[:n].copy(), np.asarray(x)[:n].copy()


def run_case(msh, x_ref, left, fixed, case):
    if case == "elastic":
        return smooth(msh, x_ref, left, fixed, method="elastic"), None
    if case == "harmonic_cg":
        return smooth(msh, x_ref, left, fixed, method="elastic", model="harmonic",
                      solver="cg", rtol=1e-13), None
    if case == "laplace":
        return smooth(msh, x_ref, left, fixed, method="laplace"), None
    if case == "repair_partial":
        r = repair(msh, x_ref, msh.geometry.x.copy(), left, fixed)
        return r.x, r
    raise ValueError(case)


def decisions(res):
    """The repair's attempts as the decisions they record, with the check's margin."""
    return [{k: a.get(k) for k in ("stage", "round", "t", "layers", "n_bad", "kept", "margin", "converged")}
            for a in res.attempts]


def main():
    comm = MPI.COMM_WORLD
    cases = [("elastic", 1.5 * H), ("harmonic_cg", 1.5 * H), ("laplace", 1.5 * H),
             ("repair_partial", 1.3)]
    for gm in (dolfinx.mesh.GhostMode.none, dolfinx.mesh.GhostMode.shared_facet):
        for case, amp in cases:
            msh, x_ref, left, fixed = setup(comm, gm, amp)
            x_par, r_par = run_case(msh, x_ref, left, fixed, case)
            # ghost rows must equal the owner's values
            v = dolfinx.la.vector(msh.geometry.index_map(), 3)
            v.array[:] = x_par.reshape(-1)
            v.scatter_forward()
            ghost_ok = comm.allreduce(bool(np.array_equal(v.array.reshape(-1, 3), x_par)),
                                      op=MPI.LAND)
            n_inv = comm.allreduce(int(inverted_cells(
                x_par, x_ref, msh.geometry.dofmaps[0][:msh.topology.index_map(2).size_local],
                2).size))
            rep_par = r_par.report.as_dict() if r_par is not None else None
            gi, gx = owned(msh, x_par)
            allgi = comm.gather(gi, root=0)
            allgx = comm.gather(gx, root=0)
            if comm.rank == 0:
                smsh, sx_ref, sleft, sfixed = setup(MPI.COMM_SELF, gm, amp)
                x_ser, r_ser = run_case(smsh, sx_ref, sleft, sfixed, case)
                order = np.argsort(smsh.geometry.input_global_indices)
                xs = x_ser[order]
                gi_all = np.concatenate(allgi)
                gx_all = np.concatenate(allgx)
                assert gi_all.size == xs.shape[0] and np.unique(gi_all).size == gi_all.size
                maxdiff = float(np.abs(gx_all - xs[gi_all]).max())
                xr = sx_ref[order][gi_all]
                on_left = (xr[:, 0] < TOL) & (xr[:, 1] > TOL) & (xr[:, 1] < 1 - TOL)
                out = {"case": case, "ghost_mode": str(gm), "maxdiff": maxdiff,
                       "maxdiff_moved": float(np.abs(gx_all - xs[gi_all])[on_left].max()),
                       "n": int(gi_all.size), "ghost_ok": ghost_ok, "n_inverted": n_inv}
                if r_par is not None:
                    keys = ("n_cells", "n_inverted_before", "n_inverted_after", "n_moved",
                            "n_shortfall")
                    out["report_par"] = {k: rep_par[k] for k in keys}
                    rs = r_ser.report.as_dict()
                    out["report_ser"] = {k: rs[k] for k in keys}
                    out["report_maxdiff"] = max(
                        abs(rep_par[k] - rs[k]) for k in ("max_displacement", "max_shortfall"))
                    out["report_mean_ratio_diff"] = abs(
                        rep_par["mean_ratio"]["min"] - rs["mean_ratio"]["min"])
                    out["stage"] = [r_par.stage, r_ser.stage]
                    out["attempts_par"] = decisions(r_par)
                    out["attempts_ser"] = decisions(r_ser)
                print(json.dumps(out), flush=True)
    # refined mesh (the situation of the refinement hook), both smoothers
    for case in ("elastic", "laplace"):
        msh, x_ref, left, fixed = setup_refined(comm, 1.5 / 32)
        x_par, _ = run_case(msh, x_ref, left, fixed, case)
        n = msh.geometry.index_map().size_local
        n_inv = comm.allreduce(int(inverted_cells(
            x_par, x_ref, msh.geometry.dofmaps[0][:msh.topology.index_map(2).size_local],
            2).size))
        n_inv0 = comm.allreduce(int(inverted_cells(
            msh.geometry.x, x_ref, msh.geometry.dofmaps[0][:msh.topology.index_map(2).size_local],
            2).size))
        allr = comm.gather(x_ref[:n], root=0)
        allx = comm.gather(x_par[:n], root=0)
        if comm.rank == 0:
            smsh, sx_ref, sleft, sfixed = setup_refined(MPI.COMM_SELF, 1.5 / 32)
            x_ser, _ = run_case(smsh, sx_ref, sleft, sfixed, case)
            r_par, x_p = by_coords(np.concatenate(allr), np.concatenate(allx))
            r_ser, x_s = by_coords(sx_ref, x_ser)
            assert np.array_equal(r_par, r_ser)
            out = {"case": "refined_" + case, "ghost_mode": "refine-default",
                   "maxdiff": float(np.abs(x_p - x_s).max()), "n": int(r_par.shape[0]),
                   "ghost_ok": True, "n_inverted": n_inv, "n_inverted_unsmoothed": n_inv0}
            print(json.dumps(out), flush=True)


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import _abort

    _abort.run(main)
