"""Curved-mesh driver used by the MPI test of ``Snapper.curved_mesh``.

Usage: python curved.py {dfg_nagata|ball_cad} LEVELS DEGREE OUT.npz
Rank 0 writes the area / volume of the degree-DEGREE mesh after LEVELS uniform
refinements, its CurvedInfo counts and the gathered coordinates of all its
geometry nodes (owned nodes only, so each node once) and of the same nodes on
the straight mesh (in 3D, uniform refinement splits the inner octahedra of
tetrahedra along partition-dependent diagonals, so nodes are compared where
their straight positions agree).
"""

import os
import sys

import mpi4py.MPI as MPI
import numpy as np
import ufl

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "meshes"))
import generate

import dolfinx.fem as fem

from nagata_snap import NagataGeometry, Snapper
from nagata_snap.cad import CadGeometry
from nagata_snap.cad.nurbs import sphere

comm = MPI.COMM_WORLD
case, levels, degree, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
if case == "dfg_nagata":
    md = generate.dfg_channel(comm, n_circle=16, h_far=0.1)
    tag = generate.CYLINDER
    geometry = NagataGeometry(md.mesh, md.facet_tags, tags=[tag])
else:
    md = generate.ball(comm, radius=1.0, h=0.5)
    tag = generate.BALL_SPHERE
    geometry = CadGeometry([sphere((0.0, 0.0, 0.0), 1.0)])
mesh, ft = md.mesh, md.facet_tags
# the ball without interior smoothing: its elastic smoothing is not partition independent
# (vertices up to 7e-3 apart between 1 and 2 processes), and this compares the curving
snapper = Snapper(mesh, ft, geometry, tags=[tag], smoothing="none" if case == "ball_cad" else "elastic")
for _ in range(levels):
    mesh, ft, *_ = snapper.refine(mesh)
cm, info = snapper.curved_mesh(degree=degree)
form = fem.form(fem.Constant(cm, 1.0) * ufl.dx(domain=cm, metadata={"quadrature_degree": 2 * degree}))
measure = comm.allreduce(fem.assemble_scalar(form))
n_own = cm.geometry.index_map().size_local
cmap = cm.geometry.cmaps[0]
x0 = fem.interpolate_geometry(mesh, fem.coordinate_element(mesh.topology.cell_type, degree, cmap.variant))
nodes = comm.gather(cm.geometry.x[:n_own], root=0)
straight = comm.gather(x0.geometry.x[:n_own], root=0)
if comm.rank == 0:
    np.savez(out, measure=measure, x=np.concatenate(nodes), x0=np.concatenate(straight),
             counts=[info.boundary_nodes, info.blended_nodes, info.reduced_nodes])
