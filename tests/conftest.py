import os
import sys

import mpi4py.MPI  # noqa: F401  (before dolfinx, see README)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
for sub in ("meshes", "demos"):
    p = os.path.join(ROOT, sub)
    if p not in sys.path:
        sys.path.insert(0, p)
