import os
import sys

import mpi4py.MPI  # noqa: F401  (before dolfinx, see README)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# the drivers the tests run in subprocesses (tests/mpi, demos, the CLI) import this checkout's
# package, not whichever one the environment has installed (a worktree beside the installed one)
os.environ["PYTHONPATH"] = os.pathsep.join(
    [ROOT] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])
for sub in ("meshes", "demos"):
    p = os.path.join(ROOT, sub)
    if p not in sys.path:
        sys.path.insert(0, p)
