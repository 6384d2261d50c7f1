"""Area/volume error of snapped straight cells vs degree-2 curved geometry.

DFG channel minus the cylinder (IGES circle, exact) and the unit ball (NURBS
sphere written to IGES), uniform refinement; CAD mode so that the exact
geometry is the reference.  Prints errors and observed orders.
"""

from __future__ import annotations

import os
import sys
import tempfile

import mpi4py.MPI as MPI
import numpy as np
import ufl

import dolfinx.fem as fem

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "meshes"))
import generate  # noqa: E402
import make_iges  # noqa: E402

from nagata_snap import Snapper  # noqa: E402
from nagata_snap.cad import CadGeometry  # noqa: E402
from nagata_snap.cad.iges import write_iges  # noqa: E402
from nagata_snap.cad.nurbs import sphere  # noqa: E402


def measure(m):
    form = fem.form(fem.Constant(m, 1.0) * ufl.dx(domain=m, metadata={"quadrature_degree": 8}))
    return m.comm.allreduce(fem.assemble_scalar(form))


def study(name, mesh, ft, geo, tag, exact, levels, comm):
    snapper = Snapper(mesh, ft, geo, tags=[tag])
    rows = []
    for k in range(levels):
        if k:
            mesh, ft, *_ = snapper.refine(mesh)
        cm, info = snapper.curved_mesh()
        rows.append((mesh.topology.index_map(mesh.topology.dim).size_global,
                     abs(measure(mesh) - exact), abs(measure(cm) - exact)))
    if comm.rank == 0:
        print(f"\n{name}")
        print(f"{'cells':>9} {'straight err':>13} {'order':>6} {'curved err':>13} {'order':>6}")
        for i, (n, es, ec) in enumerate(rows):
            os_ = f"{np.log2(rows[i - 1][1] / es):6.2f}" if i else " " * 6
            oc = f"{np.log2(rows[i - 1][2] / ec):6.2f}" if i else " " * 6
            print(f"{n:9d} {es:13.4e} {os_} {ec:13.4e} {oc}")
    return rows


def main():
    comm = MPI.COMM_WORLD
    tmp = tempfile.mkdtemp() if comm.rank == 0 else None
    tmp = comm.bcast(tmp)
    if comm.rank == 0:
        make_iges.write_dfg_circle(tmp)
        write_iges(os.path.join(tmp, "sphere.igs"), surfaces=[sphere((0.0, 0.0, 0.0), 1.0)])
    comm.barrier()
    md = generate.dfg_channel(comm, n_circle=16, h_far=0.1)
    study("DFG channel minus cylinder (area)", md.mesh, md.facet_tags,
          CadGeometry.from_iges(os.path.join(tmp, "dfg_circle.igs")), generate.CYLINDER,
          generate.DFG_LENGTH * generate.DFG_HEIGHT - np.pi * generate.DFG_RADIUS**2, 5, comm)
    md = generate.ball(comm, radius=1.0, h=0.5)
    rows = study("unit ball (volume)", md.mesh, md.facet_tags,
                 CadGeometry.from_iges(os.path.join(tmp, "sphere.igs")), generate.BALL_SPHERE,
                 4 / 3 * np.pi, 4, comm)
    if comm.rank == 0:
        print(f"\ncurved_order_ball {np.log2(rows[-2][2] / rows[-1][2]):.3f}")


if __name__ == "__main__":
    main()
