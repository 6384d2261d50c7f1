"""Run an MPI test script's ``main``: an exception on one rank aborts all ranks, success prints DONE."""

import sys
import traceback

from mpi4py import MPI


def run(main) -> None:
    """Call ``main()``; on an exception print its traceback and abort the whole job (no hang).

    When ``main`` returns on every rank, rank 0 prints ``DONE`` (the caller's
    sign that the script ran to its end).
    """
    try:
        main()
    except Exception:
        traceback.print_exc()
        sys.stdout.flush()
        MPI.COMM_WORLD.Abort(1)
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        print("DONE", flush=True)
