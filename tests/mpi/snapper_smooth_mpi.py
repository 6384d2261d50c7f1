"""MPI consistency of interior smoothing inside ``Snapper.refine`` (run under mpiexec).

Usage: ``mpiexec -n N python snapper_smooth_mpi.py [CASE ...]``; cases
``sphere`` (3D), ``sphere_tiefree`` (3D, see below), ``dfg`` (2D),
``direct3d``, ``direct3d_hard`` (inverts cells: repair stages) and
``direct2d`` (default: all).

The gmsh meshes are distributed by the DOLFINx default partitioner, i.e.
WITHOUT ghost cells (checked). ``dolfinx.mesh.refine`` adds a ghost layer
to the refined meshes; the ``direct*`` cases call
:func:`nagata_snap.smoothing.repair.repair` on the unghosted gmsh mesh itself.

Two comparisons per case, smoother and level:

``same_mesh``
    ``repair`` is spied on inside ``Snapper.refine``; its parallel inputs
    (the distributed refined mesh, reference and target coordinates, moved
    nodes, options) are gathered on rank 0, rebuilt as a serial mesh
    (``COMM_SELF``, the same cells) and ``repair`` is rerun there. The owned
    parallel result must equal the serial one to round-off for any partition,
    unless the two runs decided a marginal check differently (the attempts
    of both are printed; ``tests/test_smoothing.py`` judges them).

``serial`` (``serial_maxdiff``, ``cells_differ``)
    The whole pipeline is also run serially on rank 0. Nodes are matched by
    their reference (straight refined) position; ``cells_differ`` counts
    parallel cells (by matched nodes) that do not exist in the serial mesh.
    In 3D, ``dolfinx.mesh.refine`` (Plaza) breaks ties between equally long
    face edges by the *global vertex index*, which depends on the partition,
    so a mesh with such ties (gmsh box faces are full of them) is refined
    into a different set of tetrahedra (other interior diagonals) in
    parallel, and the smoothed coordinates legitimately differ.
    ``sphere_tiefree`` moves the interior and box-face nodes of the same
    mesh by a tiny deterministic (partition independent) amount so that no
    face has two equally long longest edges; then the refined meshes, and
    hence the smoothed coordinates, must agree with the serial run.

Rank 0 prints one JSON line per (case, method, level) and finally ``DONE``.
"""

import json
import os
import sys

import mpi4py.MPI as MPI
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "meshes"))
import generate

import basix.ufl
import dolfinx
import dolfinx.la
import dolfinx.mesh

import nagata_snap.snapper as hook
from nagata_snap import NagataGeometry, Snapper
from nagata_snap.smoothing.quality import inverted_cells
from nagata_snap.smoothing.repair import repair

WORLD = MPI.COMM_WORLD
METHODS = ("elastic", "laplace")

# -- spy on the repair call inside Snapper.refine ---------------------------------
_calls: list[dict] = []
_repair = hook.repair


def _spy(mesh, x_ref, x_target, moved, fixed, **kw):
    res = _repair(mesh, x_ref, x_target, moved, fixed, **kw)
    _calls.append({"mesh": mesh, "x_ref": np.array(x_ref), "x_target": np.array(x_target),
                   "moved": np.array(moved), "fixed": np.array(fixed), "kw": kw, "x": res.x.copy(),
                   "stage": res.stage, "attempts": decisions(res)})
    return res


hook.repair = _spy


def decisions(res):
    """The repair's attempts as the decisions they record, with the check's margin."""
    return [{k: a.get(k) for k in ("stage", "round", "t", "layers", "n_bad", "kept", "margin")}
            for a in res.attempts]


# -- meshes ----------------------------------------------------------------------
def _perturb(x):
    """Move non-boundary coordinates by <= 1e-3 (deterministic in x only).

    Coordinates at +-1 (box faces) and sphere nodes are kept, so every node
    stays on its surface; box-face nodes move within their face.
    """
    on_sphere = np.abs(np.linalg.norm(x, axis=1) - 0.5) < 1e-6
    keep = (np.abs(np.abs(x) - 1.0) < 1e-12) | on_sphere[:, None]
    a = np.array([[12.9898, 7.1, 3.3], [78.233, 1.7, 9.2], [4.1, 37.7, 2.9]])
    f = np.sin(x @ a + np.array([3.7, 1.1, 0.4]))
    x += np.where(keep, 0.0, 1e-3 * f)


def build(comm, case):
    """(mesh, facet_tags, snapped tag, levels)."""
    if case in ("sphere", "sphere_tiefree"):
        md = generate.sphere_in_box(comm, h_sphere=0.35, h_box=0.6)
        if case == "sphere_tiefree":
            _perturb(md.mesh.geometry.x)
        return md.mesh, md.facet_tags, generate.SPHERE, 2
    if case.startswith("direct3d"):
        md = generate.sphere_in_box(comm, h_sphere=0.2, h_box=0.5)
        return md.mesh, md.facet_tags, generate.SPHERE, 1
    md = generate.dfg_channel(comm, n_circle=16, h_far=0.1)
    return md.mesh, md.facet_tags, generate.CYLINDER, (3 if case == "dfg" else 1)


def owned_cells(mesh):
    return mesh.geometry.dofmaps[0][: mesh.topology.index_map(mesh.topology.dim).size_local]


# -- serial rerun of one repair call on the gathered mesh ---------------------------
def same_mesh_diff(call):
    """Max |x_parallel - x_serial| over all nodes (rank 0; None elsewhere)."""
    mesh = call["mesh"]
    comm = mesh.comm
    imap = mesh.geometry.index_map()
    n = imap.size_local
    g = imap.local_to_global(np.arange(n + imap.num_ghosts, dtype=np.int32)).astype(np.int64)
    parts = comm.gather((g[owned_cells(mesh)], g[:n], call["x_ref"][:n], call["x_target"][:n],
                         call["x"][:n], g[call["moved"]], g[call["fixed"]]), root=0)
    if comm.rank != 0:
        return None
    cells = np.concatenate([p[0] for p in parts])
    N = imap.size_global
    x_ref, x_tgt, x_par = np.zeros((N, 3)), np.zeros((N, 3)), np.zeros((N, 3))
    for p in parts:
        x_ref[p[1]], x_tgt[p[1]], x_par[p[1]] = p[2], p[3], p[4]
    moved = np.unique(np.concatenate([p[5] for p in parts]))
    fixed = np.unique(np.concatenate([p[6] for p in parts]))
    gdim = mesh.geometry.dim
    el = basix.ufl.element("Lagrange", mesh.topology.cell_name(), 1, shape=(gdim,))
    smesh = dolfinx.mesh.create_mesh(MPI.COMM_SELF, cells, el, x_ref[:, :gdim])
    order = np.asarray(smesh.geometry.input_global_indices, dtype=np.int64)
    inv = np.empty(N, dtype=np.int64)
    inv[order] = np.arange(N)
    res = repair(smesh, x_ref[order], x_tgt[order], inv[moved].astype(np.int32),
                 inv[fixed].astype(np.int32), **call["kw"])
    return float(np.abs(res.x[inv] - x_par).max()), res.stage, decisions(res)


def level_data(mesh, call):
    """Gathered (x_ref, x, cell coordinates) of owned nodes / cells (rank 0)."""
    comm = mesh.comm
    n = mesh.geometry.index_map().size_local
    x_ref = call["x_ref"]
    parts = comm.gather((x_ref[:n], mesh.geometry.x[:n], x_ref[owned_cells(mesh)]), root=0)
    if comm.rank != 0:
        return None
    return tuple(np.concatenate([p[k] for p in parts]) for k in range(3))


def ghost_ok(mesh, x):
    v = dolfinx.la.vector(mesh.geometry.index_map(), 3)
    v.array[:] = x.reshape(-1)
    v.scatter_forward()
    return mesh.comm.allreduce(bool(np.array_equal(v.array.reshape(-1, 3), x)), op=MPI.LAND)


# -- pipelines --------------------------------------------------------------------
def run_snapper(comm, case, method):
    """Per level: (level data on rank 0, same-mesh result, ghost_ok, n_inverted, stage)."""
    mesh, ft, tag, levels = build(comm, case)
    ghosts = comm.allgather(mesh.topology.index_map(mesh.topology.dim).num_ghosts)
    snapper = Snapper(mesh, ft, NagataGeometry(mesh, ft, tags=[tag]), smoothing=method)
    out = []
    for _ in range(levels):
        _calls.clear()
        mesh, *_, rep = snapper.refine(mesh)
        (call,) = _calls
        x = mesh.geometry.x
        n_inv = comm.allreduce(int(inverted_cells(x, call["x_ref"], owned_cells(mesh),
                                                  mesh.geometry.dim).size))
        same = same_mesh_diff(call) if comm.size > 1 else None
        out.append({"data": level_data(mesh, call), "same": same, "ghost_ok": ghost_ok(mesh, x),
                    "attempts": call["attempts"], "moved": rep.boundary_vertices_moved,
                    "n_inverted": n_inv, "stage": call["stage"], "ghosts_coarse": ghosts,
                    "ghosts_refined": comm.allgather(
                        mesh.topology.index_map(mesh.topology.dim).num_ghosts)})
    return out


def run_direct(comm, case, method):
    """repair() on the unghosted gmsh mesh, sphere / cylinder nodes pushed radially."""
    mesh, ft, tag, _ = build(comm, case)
    tdim = mesh.topology.dim
    ghosts = comm.allgather(mesh.topology.index_map(tdim).num_ghosts)
    mesh.topology.create_connectivity(tdim - 1, tdim)
    nodes = np.unique(dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, ft.find(tag)))
    x_ref = mesh.geometry.x.copy()
    c = np.zeros(3) if tdim == 3 else np.array([0.2, 0.2, 0.0])
    r = x_ref[nodes] - c
    rn = np.linalg.norm(r, axis=1)
    # about a third of the boundary edge length; "direct3d_hard" needs repair
    amp = {"direct3d": 0.04, "direct3d_hard": 0.2}.get(case, 0.004)
    x_t = x_ref.copy()
    x_t[nodes] = c + r * (1.0 + amp * np.cos(3 * np.arctan2(r[:, 1], r[:, 0])) / rn)[:, None]
    moved = nodes.astype(np.int32)
    fixed = np.zeros(0, np.int32)
    res = repair(mesh, x_ref, x_t, moved, fixed, method=method)
    call = {"mesh": mesh, "x_ref": x_ref, "x_target": x_t, "moved": moved, "fixed": fixed,
            "kw": {"method": method}, "x": res.x, "stage": res.stage, "attempts": decisions(res)}
    n_inv = comm.allreduce(int(inverted_cells(res.x, x_ref, owned_cells(mesh), tdim).size))
    n_changed = comm.allreduce(int(np.count_nonzero(
        np.any(res.x != x_t, axis=1)[: mesh.geometry.index_map().size_local])))
    same = same_mesh_diff(call) if comm.size > 1 else None
    return [{"same": same, "ghost_ok": ghost_ok(mesh, res.x), "n_inverted": n_inv,
             "attempts": call["attempts"],
             "stage": res.stage, "ghosts_coarse": ghosts, "n_smoothed": n_changed}]


def compare(par, ser):
    """Serial vs parallel pipeline at one level.

    Returns (ref_matched, serial_maxdiff, cells_differ, pointset_maxdiff):
    nodes are matched by their reference (straight refined) position; if
    that is not a bijection (the previous levels already differ)
    ``ref_matched`` is False, ``serial_maxdiff`` / ``cells_differ`` are None
    and only the point-set distance of the final coordinates is given.
    """
    xr_p, x_p, cells_p = par
    xr_s, x_s, cells_s = ser
    dp, _ = cKDTree(x_s).query(x_p)
    pointset = float(dp.max())
    tree = cKDTree(xr_s)
    d, i = tree.query(xr_p)
    if not (xr_p.shape == xr_s.shape and d.max() < 1e-10 and np.unique(i).size == i.size):
        return False, None, None, pointset
    diff = float(np.abs(x_p - x_s[i]).max())
    nv = cells_p.shape[1]
    _, kp = tree.query(cells_p.reshape(-1, 3))
    _, ks = tree.query(cells_s.reshape(-1, 3))
    kp = np.ascontiguousarray(np.sort(kp.reshape(-1, nv), axis=1))
    ks = np.ascontiguousarray(np.sort(ks.reshape(-1, nv), axis=1))
    rec = [("", kp.dtype)] * nv
    common = np.intersect1d(kp.view(rec), ks.view(rec))
    return True, diff, int(kp.shape[0] - common.size), pointset


def main():
    cases = sys.argv[1:] or ["sphere", "sphere_tiefree", "dfg", "direct3d", "direct3d_hard",
                             "direct2d"]
    for case in cases:
        for method in METHODS:
            if case.startswith("direct"):
                par = run_direct(WORLD, case, method)
                ser = None
            else:
                par = run_snapper(WORLD, case, method)
                ser = run_snapper(MPI.COMM_SELF, case, method) if WORLD.rank == 0 else None
            WORLD.barrier()
            if WORLD.rank != 0:
                continue
            for k, lev in enumerate(par):
                out = {"case": case, "method": method, "level": k + 1, "size": WORLD.size,
                       "ghosts_coarse": lev["ghosts_coarse"], "stage": lev["stage"],
                       "ghost_ok": lev["ghost_ok"], "n_inverted": lev["n_inverted"]}
                out["attempts"] = lev["attempts"]
                if lev["same"] is not None:
                    (out["same_mesh_maxdiff"], out["stage_serial_rerun"],
                     out["attempts_serial_rerun"]) = lev["same"]
                if "n_smoothed" in lev:
                    out["n_smoothed"] = lev["n_smoothed"]
                if ser is not None:
                    out["ghosts_refined"] = lev["ghosts_refined"]
                    out["n_nodes"] = int(lev["data"][0].shape[0])
                    (out["ref_matched"], out["serial_maxdiff"], out["cells_differ"],
                     out["pointset_maxdiff"]) = compare(lev["data"], ser[k]["data"])
                    out["n_inverted_serial"] = ser[k]["n_inverted"]
                    out["moved"], out["moved_serial"] = lev["moved"], ser[k]["moved"]
                print(json.dumps(out), flush=True)


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import _abort

    _abort.run(main)
