"""Run an MPI test script's ``main`` so that an exception on one rank aborts all ranks."""

import sys
import traceback

from mpi4py import MPI


def run(main) -> None:
    """Call ``main()``; on an exception print its traceback and abort the whole job (no hang)."""
    try:
        main()
    except Exception:
        traceback.print_exc()
        sys.stdout.flush()
        MPI.COMM_WORLD.Abort(1)
