"""NagataGeometry's normals and coefficients on a partitioned 3D mesh (used by tests/test_normals.py).

Usage: python nagata_normals.py OUT.npz
A box with a cylindrical hole (flat faces, box edges, curved hole, rims):
rank 0 writes the canonical facet ids, corner normals and edge coefficients;
``ranks_agree`` says whether every process computed the same bytes.
"""

import os
import sys

import mpi4py.MPI as MPI
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "meshes"))
import generate  # noqa: E402

from nagata_snap import NagataGeometry  # noqa: E402

comm = MPI.COMM_WORLD
md = generate.cylinder_in_box(comm, h_cylinder=0.04, h_box=0.2)
geo = NagataGeometry(md.mesh, md.facet_tags)
data = [geo.ids.tobytes(), geo.corner_normal.tobytes(), geo.coef.tobytes()]
agree = all(d == data for d in comm.allgather(data))
if comm.rank == 0:
    np.savez(sys.argv[1], ids=geo.ids, normals=geo.corner_normal, coef=geo.coef, ranks_agree=agree)
