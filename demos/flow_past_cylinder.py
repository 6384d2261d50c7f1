"""Flow past a cylinder (DFG 2D-1): adaptive refinement with and without snapping.

The steady Navier-Stokes benchmark of Schaefer & Turek (1996) is solved in an
adaptive loop

    solve -> estimate -> mark (Doerfler) -> refine [-> snap] -> solve ...

four times, side by side, from the same coarse gmsh mesh (the cylinder a
polygon of ``--n-circle`` segments):

* ``none``:   plain ``dolfinx.mesh.refine``: new cylinder vertices stay on the
              straight edges of the coarse polygon, so c_D converges to the
              drag of that polygon and the error stalls;
* ``nagata``: ``nagata_snap.Snapper`` with ``NagataGeometry`` built on the
              coarse mesh (no CAD), snapping the CYLINDER facets only;
* ``iges``:   ``nagata_snap.Snapper`` with ``CadGeometry.from_iges`` of the
              exact NURBS circle ``dfg_circle.igs`` (written by
              ``meshes/make_iges.py``), CYLINDER facets only.  If
              ``nagata_snap.cad`` cannot be imported or the run fails, a line
              says that the IGES run was skipped and why;
* ``iges-p2``: the same meshes as ``iges`` (its marks are replayed), but the
              flow is solved on ``Snapper.curved_mesh()``: degree-2 geometry
              with the cylinder's edge mid-nodes on the NURBS circle.

Solver, indicator and marking are those of ``demos/dfg.py``: Taylor-Hood
P2/P1, Newton with MUMPS, started from the previous level's velocity (carried
to the refined mesh by ``Snapper.transfer``: through the parent cells, no
point search, no zero-filled dofs where the snapped boundary left the old
mesh; the plain run interpolates non-matching, its levels are nested),
drag/lift from the volume (residual) form, the residual error indicator, and
Doerfler marking of the cells carrying the fraction ``--theta`` of
sum eta_K^2.  Reference values: John & Matthies (2001).

For the modes in ``--zero-start`` (default ``iges iges-p2``: straight and
curved meshes) every level is solved a second time from zero, only to count
Newton iterations: the table prints them as ``transferred/zero``.

Examples::

    python demos/flow_past_cylinder.py
    python demos/flow_past_cylinder.py                 # plot: out/flow_cd.png
    python demos/flow_past_cylinder.py --levels 4 --theta 0.4 --json out.json --plot cd.png
    mpiexec -n 2 python demos/flow_past_cylinder.py --modes none nagata --out results/
                                                       # results/flow_cd.png, results/*.bp (VTX)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys
import tempfile
import time

import mpi4py.MPI as MPI  # must precede dolfinx/petsc4py

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

import dolfinx  # noqa: E402
import dolfinx.io  # noqa: E402
import dolfinx.mesh  # noqa: E402

import nagata_snap  # noqa: E402
from demos.dfg import (  # noqa: E402
    C_D_REF,
    C_L_REF,
    CYLINDER,
    DP_REF,
    _point_values,
    dorfler_mark,
    ns_residual_indicator,
    solve_dfg,
)
from meshes import generate  # noqa: E402

MODES = ("none", "nagata", "iges", "iges-p2")
LABELS = {
    "none": "no snapping (dolfinx.mesh.refine)",
    "nagata": "Nagata snapping (no CAD)",
    "iges": "IGES snapping (NURBS circle)",
    "iges-p2": "IGES snapping, solved on the degree-2 curved mesh (same meshes as iges)",
}

#: DFG 2D-1 on gmsh meshes regenerated on the true circle at each level
#: (DESIGN.md, independent P2/P1 solver): (dofs, relative c_D error).
REGENERATED_REFERENCE = [(10_000, 3.8e-3), (39_000, 1.0e-3), (152_000, 2.3e-4)]
#: plain refinement of a 16-gon stalls at this relative c_D error (DESIGN.md).
POLYGON_STALL = 1.3e-2

CENTRE = np.array(generate.DFG_CENTER)
RADIUS = generate.DFG_RADIUS


# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------
def say(comm, *args, quiet: bool = False) -> None:
    """Print on rank 0 (flushed) unless ``quiet``."""
    if comm.rank == 0 and not quiet:
        print(*args, flush=True)


def cylinder_distance(mesh, facet_tags) -> float:
    """Largest distance of a CYLINDER facet vertex from the true circle (global)."""
    fdim = mesh.topology.dim - 1
    facets = facet_tags.find(CYLINDER)
    if len(facets):
        nodes = np.unique(dolfinx.mesh.entities_to_geometry(mesh, fdim, facets))
        x = mesh.geometry.x[nodes]
        d = float(np.abs(np.hypot(x[:, 0] - CENTRE[0], x[:, 1] - CENTRE[1]) - RADIUS).max())
    else:
        d = 0.0
    return mesh.comm.allreduce(d, op=MPI.MAX)


def plain_refine(mesh, facet_tags, edges):
    """``dolfinx.mesh.refine`` with facet-tag transfer (no snapping)."""
    mesh.topology.create_entities(1)
    mesh1, parent_cell, parent_facet = dolfinx.mesh.refine(
        mesh, edges, partitioner=None,
        option=dolfinx.mesh.RefinementOption.parent_cell_and_facet,
    )
    mesh1.topology.create_entities(mesh1.topology.dim - 1)
    tags1 = dolfinx.mesh.transfer_meshtag(facet_tags, mesh1, parent_cell, parent_facet)
    return mesh1, tags1


def initial_guess(snapper, u_prev, mesh):
    """The previous level's velocity for the Newton start on ``mesh`` (None at level 0).

    With snapping: ``Snapper.transfer`` onto ``mesh`` (straight, or the curved
    mesh of the refined level when ``u_prev`` lives on the previous curved
    mesh).  Without: ``u_prev`` itself (``solve_dfg`` interpolates it
    non-matching; plain refinement is nested, so no point falls outside).
    """
    if u_prev is None or snapper is None:
        return u_prev
    V = dolfinx.fem.functionspace(mesh, u_prev.function_space.ufl_element())
    return snapper.transfer(u_prev, V)


def make_geometry(mode, mesh, facet_tags, iges_path):
    """The snapping geometry of ``mode`` (None for plain refinement)."""
    if mode == "none":
        return None
    if mode == "nagata":
        return nagata_snap.NagataGeometry(mesh, facet_tags, tags=[CYLINDER])
    # "iges" and "iges-p2"
    from nagata_snap.cad import CadGeometry  # ImportError -> IGES run skipped

    return CadGeometry.from_iges(iges_path, dim=2)


def write_iges_file(comm, directory: str) -> str:
    """Write ``dfg_circle.igs`` into ``directory`` (rank 0) and return its path."""
    err = None
    path = None
    if comm.rank == 0:
        try:
            from meshes import make_iges

            path = str(make_iges.write_dfg_circle(directory))
        except Exception as e:  # reported as a skipped IGES run
            err = f"{type(e).__name__}: {e}"
    path, err = comm.bcast((path, err), root=0)
    if err:
        raise RuntimeError(f"could not write dfg_circle.igs ({err})")
    return path


# --------------------------------------------------------------------------
# one adaptive run
# --------------------------------------------------------------------------
def run(mode: str, args, comm, iges_path: str | None, replay: list | None = None) -> dict:
    """Adaptive loop of one mode; returns {"status", "reason", "levels", ...}.

    ``replay``: marked edges per level of another run to reuse (the degree-2
    run refines exactly like the straight IGES run, so both are compared on
    the same meshes; its own indicator would be evaluated on straight cells).
    """
    out = {"mode": mode, "label": LABELS[mode], "status": "ok", "reason": None, "levels": [],
           "marked_edges": []}
    quiet = args.quiet
    say(comm, f"\n=== {mode}: {LABELS[mode]} ===", quiet=quiet)
    t0 = time.perf_counter()
    data = generate.dfg_channel(comm, n_circle=args.n_circle, h_far=args.h_far)
    mesh, ft = data.mesh, data.facet_tags
    out["mesh_time"] = time.perf_counter() - t0
    snapper = None
    t0 = time.perf_counter()
    try:
        geometry = make_geometry(mode, mesh, ft, iges_path)
        if geometry is not None:
            snapper = nagata_snap.Snapper(mesh, ft, geometry, tags=[CYLINDER])
    except Exception as e:
        if not mode.startswith("iges"):
            raise
        out.update(status="skipped", reason=f"{type(e).__name__}: {e}")
        say(comm, f"IGES run skipped: {out['reason']}")
        return out
    out["setup_time"] = time.perf_counter() - t0

    u_prev = None
    for level in range(args.levels + 1):
        row = {"level": level}
        times = {}
        t0 = time.perf_counter()
        if mode.endswith("-p2"):
            # solve on the degree-2 mesh (same topology and facet tags as `mesh`)
            cmesh, _ = snapper.curved_mesh()
            times["curve"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            u0 = initial_guess(snapper, u_prev, cmesh)  # previous curved level -> this one
            times["transfer"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            res = solve_dfg(cmesh, ft, initial_guess=u0)
            u_next = res.u
            # the indicator works on straight cells: same dofs on the straight mesh
            u_s = dolfinx.fem.Function(dolfinx.fem.functionspace(mesh, res.u.function_space.ufl_element()))
            p_s = dolfinx.fem.Function(dolfinx.fem.functionspace(mesh, res.p.function_space.ufl_element()))
            u_s.x.array[:] = res.u.x.array
            p_s.x.array[:] = res.p.x.array
            # both pressure points are vertices of the cylinder polygon: evaluate on the
            # straight copy (same nodal values), where point location is exact
            pv, _ = _point_values(p_s, np.array([[0.15, 0.2, 0.0], [0.25, 0.2, 0.0]]))
            dp = float(pv[0] - pv[1])
            res = dataclasses.replace(res, dp=dp, err_dp=abs(dp - DP_REF) / abs(DP_REF))
        else:
            u0 = initial_guess(snapper, u_prev, mesh)
            times["transfer"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            res = solve_dfg(mesh, ft, initial_guess=u0)
            u_s, p_s = res.u, res.p
            u_next = u_s
        times["solve"] = time.perf_counter() - t0
        newton_zero = c_D_zero = None
        if level > 0 and mode in args.zero_start:  # the same level from zero, for comparison
            t0 = time.perf_counter()
            res0 = solve_dfg(cmesh if mode.endswith("-p2") else mesh, ft)
            newton_zero, c_D_zero = res0.newton_iterations, res0.c_D
            times["zero_start"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        eta = ns_residual_indicator(u_s, p_s, ft)
        n_owned = mesh.topology.index_map(mesh.topology.dim).size_local
        eta_total = float(np.sqrt(comm.allreduce(float(np.sum(eta.x.array[:n_owned] ** 2)))))
        times["estimate"] = time.perf_counter() - t0
        row.update(
            dofs=res.dofs, cells=res.num_cells, c_D=res.c_D, c_L=res.c_L, dp=res.dp,
            err_c_D=res.err_c_D, err_c_L=res.err_c_L, err_dp=res.err_dp,
            c_D_surface=res.c_D_surface, err_c_D_surface=res.err_c_D_surface,
            newton_iterations=res.newton_iterations, newton_iterations_zero=newton_zero,
            c_D_zero=c_D_zero, eta=eta_total,
            cylinder_distance=cylinder_distance(mesh, ft),
        )
        last = level == args.levels
        snap_info = None
        if not last:
            t0 = time.perf_counter()
            if replay is not None:
                edges = replay[level]  # the straight-cell run's marks: same meshes, side by side
            else:
                edges = dorfler_mark(mesh, eta, args.theta)
            out["marked_edges"].append(edges)
            times["mark"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            if snapper is None:
                mesh1, ft1 = plain_refine(mesh, ft, edges)
                times["refine"] = time.perf_counter() - t0
                times["snap"] = 0.0
            else:
                try:
                    mesh1, ft1, _, _, report = snapper.refine(mesh, edges)
                except Exception as e:
                    if not mode.startswith("iges"):
                        raise
                    row["times"] = times
                    out["levels"].append(row)
                    out.update(status="failed", reason=f"{type(e).__name__}: {e}")
                    say(comm, f"IGES run stopped at level {level}: {out['reason']}")
                    return out
                wall = time.perf_counter() - t0
                times["refine"] = report.times.get("refine", 0.0)
                times["snap"] = wall - times["refine"]  # lineage + place + check + tags
                snap_info = {
                    "report_times": dict(report.times),
                    "boundary_vertices_moved": report.boundary_vertices_moved,
                    "max_displacement": report.max_displacement,
                }
        row["times"] = times
        if snap_info is not None:
            row["snap"] = snap_info
        out["levels"].append(row)
        tline = ", ".join(f"{k} {v:.2f}s" for k, v in times.items())
        say(
            comm,
            f"[{mode}] level {level}: {res.dofs:7d} dofs  c_D {res.c_D:.6f}  c_L {res.c_L:.6f}  "
            f"dp {res.dp:.6f} | rel. err c_D {res.err_c_D:.2e}  c_L {res.err_c_L:.2e}  "
            f"dp {res.err_dp:.2e} | cyl. dist {row['cylinder_distance']:.1e} | "
            f"Newton {res.newton_iterations}"
            + (f" (from zero {newton_zero})" if newton_zero is not None else "") + f" | {tline}",
            quiet=quiet,
        )
        if last:
            out["final"] = (mesh, ft, u_s, p_s, eta)
        else:
            u_prev = u_next
            mesh, ft = mesh1, ft1
    return out


# --------------------------------------------------------------------------
# output
# --------------------------------------------------------------------------
def comparison_table(runs: dict, modes: list[str]) -> str:
    """Rows = levels; per mode: dofs, relative errors of c_D, c_L, dp, and Newton iterations
    (``transferred/zero`` where the zero start was counted too)."""
    nlev = max((len(runs[m]["levels"]) for m in modes), default=0)
    head1 = f"{'':>5}"
    head2 = f"{'level':>5}"
    for m in modes:
        head1 += f" | {m:^44}"
        head2 += f" | {'dofs':>7} {'err c_D':>9} {'err c_L':>9} {'err dp':>9} {'Newton':>6}"
    lines = [
        f"relative errors vs. reference c_D = {C_D_REF}, c_L = {C_L_REF}, dp = {DP_REF}; "
        "Newton iterations from the transferred previous level / from zero",
        head1, head2, "-" * len(head2),
    ]
    for k in range(nlev):
        s = f"{k:5d}"
        for m in modes:
            lv = runs[m]["levels"]
            if k < len(lv):
                r = lv[k]
                its = str(r["newton_iterations"])
                if r.get("newton_iterations_zero") is not None:
                    its += f"/{r['newton_iterations_zero']}"
                s += (f" | {r['dofs']:7d} {r['err_c_D']:9.2e} {r['err_c_L']:9.2e} "
                      f"{r['err_dp']:9.2e} {its:>6}")
            else:
                s += f" | {'-':>7} {'-':>9} {'-':>9} {'-':>9} {'-':>6}"
        lines.append(s)
    for m in modes:
        if runs[m]["status"] != "ok":
            lines.append(f"{m}: {runs[m]['status']} ({runs[m]['reason']})")
    return "\n".join(lines)


def timing_table(runs: dict, modes: list[str]) -> str:
    """Total wall time per stage and mode (summed over levels; the zero-start solves that
    only count Newton iterations are listed apart)."""
    stages = ("solve", "estimate", "mark", "refine", "snap", "transfer")
    lines = [f"{'time [s]':>9}" + "".join(f" {s:>9}" for s in stages) + f" {'total':>9}"]
    for m in modes:
        lv = runs[m]["levels"]
        if not lv:
            continue
        tot = [sum(r["times"].get(s, 0.0) for r in lv) for s in stages]
        zero = sum(r["times"].get("zero_start", 0.0) for r in lv)
        lines.append(f"{m:>9}" + "".join(f" {t:9.2f}" for t in tot) + f" {sum(tot):9.2f}"
                     + (f"   (+ {zero:.2f} s zero-start solves)" if zero else ""))
    return "\n".join(lines)


def write_plot(path: str, runs: dict, modes: list[str], args) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    style = {"none": ("o-", "tab:red"), "nagata": ("s-", "tab:blue"), "iges": ("^--", "tab:green"),
             "iges-p2": ("D-", "tab:purple")}
    for m in modes:
        lv = runs[m]["levels"]
        if not lv:
            continue
        fmt, color = style[m]
        ax.loglog([r["dofs"] for r in lv], [r["err_c_D"] for r in lv], fmt, color=color,
                  label=LABELS[m], markerfacecolor="none" if m == "iges" else color)
    ref = np.array(REGENERATED_REFERENCE, dtype=float)
    ax.loglog(ref[:, 0], ref[:, 1], "kx", markersize=9, mew=2,
              label="meshes regenerated on the true circle (DESIGN.md)")
    ax.set_xlabel("degrees of freedom (P2/P1)")
    ax.set_ylabel(r"relative error of $c_D$")
    ax.set_title(f"DFG 2D-1, adaptive (Doerfler theta = {args.theta}), "
                 f"coarse cylinder {args.n_circle}-gon", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=150)
    plt.close(fig)


def write_output(directory: str, mode: str, final, comm) -> list[str]:
    """Final mesh + facet tags (XDMF), velocity, pressure and indicator (VTX)."""
    import basix.ufl

    mesh, ft, u, p, eta = final
    os.makedirs(directory, exist_ok=True)
    files = []
    mesh.topology.create_connectivity(mesh.topology.dim - 1, mesh.topology.dim)
    xdmf = os.path.join(directory, f"{mode}_mesh.xdmf")
    with dolfinx.io.XDMFFile(comm, xdmf, "w") as f:
        mesh.name = "mesh"
        ft.name = "facet_tags"
        f.write_mesh(mesh)
        f.write_meshtags(ft, mesh.geometry)
    files.append(xdmf)
    # velocity: interpolate into a P2 vector space (the collapsed sub-space
    # already is one; interpolation makes the output independent of that)
    V = dolfinx.fem.functionspace(
        mesh, basix.ufl.element("Lagrange", mesh.basix_cell(), 2, shape=(mesh.geometry.dim,))
    )
    uo = dolfinx.fem.Function(V, name="velocity")
    uo.interpolate(u)
    p.name = "pressure"
    eta.name = "eta"
    for name, fn in (("velocity", uo), ("pressure", p), ("eta", eta)):
        path = os.path.join(directory, f"{mode}_{name}.bp")
        with dolfinx.io.VTXWriter(comm, path, [fn], engine="BP4") as w:
            w.write(0.0)
        files.append(path)
    return files


# --------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------
def parse_args(argv=None):
    parser = argparse.ArgumentParser(
        prog="flow_past_cylinder.py",
        description=(
            "DFG 2D-1 flow past a cylinder: adaptive loop (solve, residual indicator, "
            "Doerfler marking, refine) with plain dolfinx.mesh.refine, Nagata snapping and "
            "IGES snapping of the cylinder, side by side.  Prints dofs, c_D, c_L, dp and their "
            "relative errors per level and a comparison table."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--levels", type=int, default=10,
                        help="number of adaptive refinements (the loop solves levels+1 meshes)")
    parser.add_argument("--theta", type=float, default=0.5,
                        help="Doerfler bulk parameter in (0, 1]: mark the fewest cells carrying "
                             "this fraction of sum eta_K^2 (1 = refine everywhere)")
    parser.add_argument("--n-circle", type=int, default=16,
                        help="segments of the cylinder polygon in the coarse mesh")
    parser.add_argument("--h-far", type=float, default=0.04,
                        help="far-field mesh size of the coarse mesh [m]")
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES),
                        metavar="MODE",
                        help="runs to do, any of: none (plain refine), nagata (Nagata patches "
                             "from the coarse mesh), iges (NURBS circle from dfg_circle.igs), "
                             "iges-p2 (the iges meshes, solved on their degree-2 curved version)")
    parser.add_argument("--zero-start", nargs="*", choices=MODES, default=["iges", "iges-p2"],
                        metavar="MODE",
                        help="modes whose levels are also solved from zero, to count Newton "
                             "iterations against the transferred start (none: no extra solves)")
    parser.add_argument("--json", metavar="FILE",
                        help="write every level of every run (dofs, c_D, c_L, dp, relative "
                             "errors, seconds per stage solve/estimate/mark/refine/snap) as JSON")
    parser.add_argument("--plot", metavar="FILE.png",
                        help="where to write the plot of the relative c_D error against dofs "
                             "(log-log, matplotlib, with the regenerated-mesh reference points of "
                             "DESIGN.md); default DIR/flow_cd.png with --out DIR, else out/flow_cd.png")
    parser.add_argument("--no-plot", action="store_true", help="write no plot")
    parser.add_argument("--out", metavar="DIR",
                        help="write each run's last level: mesh and facet tags (MODE_mesh.xdmf) and "
                             "velocity, pressure and indicator (MODE_*.bp, VTX) for ParaView; "
                             "dfg_circle.igs is written there too")
    parser.add_argument("--quiet", action="store_true",
                        help="print only the final tables (and skipped runs)")
    args = parser.parse_args(argv)
    if args.levels < 0:
        parser.error("--levels must be >= 0")
    if not 0.0 < args.theta <= 1.0:
        parser.error("--theta must be in (0, 1]")
    if args.n_circle < 3:
        parser.error("--n-circle must be >= 3")
    if args.h_far <= 0.0:
        parser.error("--h-far must be > 0")
    args.modes = [m for m in MODES if m in args.modes]  # fixed order, no duplicates
    if args.no_plot:
        args.plot = None
    elif args.plot is None:
        args.plot = os.path.join(args.out or "out", "flow_cd.png")
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    comm = MPI.COMM_WORLD
    t_start = time.perf_counter()
    say(comm, f"DFG 2D-1 adaptive loop: {args.levels} refinements, theta = {args.theta}, "
              f"coarse {args.n_circle}-gon, h_far = {args.h_far}, modes {' '.join(args.modes)}, "
              f"{comm.size} MPI process(es)", quiet=args.quiet)

    tmpdir = None
    iges_path = None
    runs = {}
    if any(m.startswith("iges") for m in args.modes):
        if args.out:
            directory = args.out
            if comm.rank == 0:
                os.makedirs(directory, exist_ok=True)
        else:
            tmpdir = comm.bcast(tempfile.mkdtemp(prefix="dfg_iges_") if comm.rank == 0 else None)
            directory = tmpdir
        try:
            import nagata_snap.cad  # noqa: F401

            iges_path = write_iges_file(comm, directory)
        except Exception as e:
            for m in (m for m in args.modes if m.startswith("iges")):
                runs[m] = {"mode": m, "label": LABELS[m], "status": "skipped",
                           "reason": f"{type(e).__name__}: {e}", "levels": []}
            say(comm, f"IGES runs skipped: {type(e).__name__}: {e}")
    try:
        for mode in args.modes:
            if mode not in runs:
                straight = runs.get("iges", {})
                replay = None
                if mode == "iges-p2" and straight.get("status") == "ok":
                    replay = straight["marked_edges"]
                runs[mode] = run(mode, args, comm, iges_path, replay)
    finally:
        if tmpdir is not None:
            comm.barrier()
            if comm.rank == 0:
                shutil.rmtree(tmpdir, ignore_errors=True)

    if args.out:
        for mode in args.modes:
            final = runs[mode].pop("final", None)
            if final is not None:
                files = write_output(args.out, mode, final, comm)
                say(comm, f"{mode}: wrote {', '.join(files)}", quiet=args.quiet)
    for mode in args.modes:
        runs[mode].pop("final", None)
        runs[mode].pop("marked_edges", None)

    say(comm, "\n" + comparison_table(runs, args.modes))
    say(comm, "\n" + timing_table(runs, args.modes))
    total = time.perf_counter() - t_start
    say(comm, f"total wall time {total:.1f} s on {comm.size} process(es)")

    result = {
        "config": {
            "levels": args.levels, "theta": args.theta, "n_circle": args.n_circle,
            "h_far": args.h_far, "modes": args.modes, "mpi_size": comm.size,
        },
        "reference": {"c_D": C_D_REF, "c_L": C_L_REF, "dp": DP_REF,
                      "regenerated_c_D_error": REGENERATED_REFERENCE},
        "runs": runs,
        "total_time": total,
    }
    if comm.rank == 0:
        if args.json:
            with open(args.json, "w") as fh:
                json.dump(result, fh, indent=1)
            say(comm, f"wrote {args.json}", quiet=args.quiet)
        if args.plot:
            try:
                os.makedirs(os.path.dirname(os.path.abspath(args.plot)), exist_ok=True)
                write_plot(args.plot, runs, args.modes, args)
                say(comm, f"wrote the c_D convergence plot to {os.path.abspath(args.plot)}")
            except ImportError as e:
                print(f"plot not written: {e} (pip install matplotlib)", file=sys.stderr, flush=True)
    return result


if __name__ == "__main__":
    main()
