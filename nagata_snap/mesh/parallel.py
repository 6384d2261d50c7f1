"""Collective error handling: an exception on one process is raised on all of them."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import mpi4py.MPI as MPI
import numpy as np

from nagata_snap.errors import CadError

if TYPE_CHECKING:
    from nagata_snap.geometry import PlaceReport, SnapGeometry
    from nagata_snap.mesh.records import Records


def collective(comm: MPI.Comm, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """Call ``fn(*args, **kwargs)`` on every process; if it raises on any, raise on all.

    The process that failed re-raises its own exception; the others raise an
    exception of the same class (``RuntimeError`` if that class cannot be
    built from a message) whose message ends in "(raised on another
    process)". ``fn`` must not itself call collective MPI operations after a
    point where it can fail on some processes only (they would wait forever).

    Returns:
        What ``fn`` returned.
    """
    err = None
    try:
        out = fn(*args, **kwargs)
    except Exception as exc:  # re-raised below, on every process
        err = exc
    errors = comm.allgather(None if err is None else (type(err), str(err)))
    if err is not None:
        raise err
    for e in errors:
        if e is not None:
            cls, msg = e
            try:
                raise cls(f"{msg} (raised on another process)")
            except TypeError:
                raise RuntimeError(f"{cls.__name__}: {msg} (raised on another process)") from None
    return out


def collective_place(
    comm: MPI.Comm, geometry: SnapGeometry, records: Records, straight: np.ndarray, what: str
) -> tuple[np.ndarray, Records, PlaceReport]:
    """``geometry.place(records, straight)`` on every process (see :func:`collective`).

    Raises:
        CadError: on every process, if any point found no acceptable CAD
            projection (``report.n_unresolved``); ``what`` names the points.

    Returns:
        What ``place`` returned: ``(points, records, report)``.
    """
    pts, recs, report = collective(comm, geometry.place, records, straight)
    unresolved = comm.allreduce(report.n_unresolved)
    if unresolved:
        raise CadError(
            f"{unresolved} {what} have no acceptable projection onto the CAD geometry (Newton "
            "and every fallback failed or landed farther than the local edge length); nothing "
            "was returned"
        )
    return pts, recs, report
