"""NagataGeometry's normals and coefficients on a partitioned 3D mesh (used by tests/test_normals.py).

Usage: python nagata_normals.py OUT.npz [estimated|cad]
``estimated``: a box with a cylindrical hole (flat faces, box edges, curved
hole, rims), estimated normals; ``cad``: ``plate_filleted`` as STEP through
``nagata_snap.cad.mesh_cad``, the ``CadGeometry``'s normals.  Rank 0 writes
the canonical facet ids, corner normals and edge coefficients; ``ranks_agree``
says whether every process computed the same bytes.
"""

import os
import sys

import mpi4py.MPI as MPI
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "meshes"))
import generate
import parts

from nagata_snap import NagataGeometry
from nagata_snap.cad import mesh_cad

comm = MPI.COMM_WORLD
if sys.argv[2:] == ["cad"]:
    path = os.path.join(os.path.dirname(sys.argv[1]), "plate_filleted.step")
    if comm.rank == 0:
        parts.write_part("plate_filleted", os.path.dirname(sys.argv[1]), formats=("step",))
    comm.barrier()
    cm, cad = mesh_cad(path, comm, curvature=12)
    geo = NagataGeometry(cm.mesh, cm.facet_tags, normals=cad)
else:
    md = generate.cylinder_in_box(comm, h_cylinder=0.04, h_box=0.2)
    geo = NagataGeometry(md.mesh, md.facet_tags)
data = [geo.ids.tobytes(), geo.corner_normal.tobytes(), geo.coef.tobytes()]
agree = all(d == data for d in comm.allgather(data))
if comm.rank == 0:
    np.savez(sys.argv[1], ids=geo.ids, normals=geo.corner_normal, coef=geo.coef, ranks_agree=agree)
