"""Collective error handling: an exception on one process is raised on all of them."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import dolfinx.common
import dolfinx.la
import mpi4py.MPI as MPI
import numpy as np

from nagata_snap.errors import CadError
from nagata_snap.mesh.records import Records

if TYPE_CHECKING:
    from nagata_snap.geometry import PlaceReport, SnapGeometry


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


def split_facets(imap: dolfinx.common.IndexMap, nodes: np.ndarray) -> np.ndarray:
    """``(nf,)`` bool: the facets ``nodes (nf, nfv)`` (local nodes of ``imap``) with a node that
    facets of another process share (collective).

    A vertex on a process boundary has facets on several processes; each
    sees only its own unless they are exchanged (:func:`collective_place`).
    """
    nodes = np.asarray(nodes)
    if nodes.ndim == 1:
        nodes = nodes[:, None]
    if imap.comm.size == 1:
        return np.zeros(len(nodes), dtype=bool)
    v = dolfinx.la.vector(imap, 1)
    v.array[:] = 0.0
    v.array[np.unique(nodes)] = 1.0  # this process has facets at the node
    v.scatter_reverse(dolfinx.la.InsertMode.add)  # owners: the number of such processes
    v.scatter_forward()
    return (v.array[nodes] > 1.5).any(axis=1)


def collective_place(
    comm: MPI.Comm, geometry: SnapGeometry, records: Records, straight: np.ndarray, what: str,
    split: np.ndarray | None = None,
) -> tuple[np.ndarray, Records, PlaceReport]:
    """``geometry.place(records, straight)`` on every process (see :func:`collective`).

    ``split (nf,)`` bool marks the facets at vertices shared with other
    processes (:func:`split_facets`): every process places them along with
    its own facets, so that each such vertex is placed from all its facets
    (slots), on every process alike, as in a serial run: a vertex's
    position depends on all its facets (the faces they are on, its CAD edge
    or corner, its best slot).  They are gathered on every process (cost
    ``O(processes x facets on process boundaries)``).

    Raises:
        CadError: on every process, if any point found no acceptable CAD
            projection (``report.n_unresolved``); ``what`` names the points.

    Returns:
        What ``place`` returned for this process's facets: ``(points, records,
        report)`` (the report counts the other processes' facets placed here too).
    """
    nf = len(records.root)
    if split is not None and comm.size > 1:
        split = np.asarray(split, dtype=bool)
        parts = comm.allgather((records.root[split], records.params[split], np.asarray(straight)[split]))
        other = [q for r, q in enumerate(parts) if r != comm.rank and len(q[0])]
        if other:  # (a process without facets has arrays of no particular shape)
            own = [(records.root, records.params, np.asarray(straight))] if nf else []
            both = own + other
            records = Records(np.concatenate([q[0] for q in both]), np.concatenate([q[1] for q in both]))
            straight = np.concatenate([q[2] for q in both])
    pts, recs, report = collective(comm, geometry.place, records, straight)
    pts, recs = pts[:nf], recs.take(np.arange(nf))
    unresolved = comm.allreduce(report.n_unresolved)
    if unresolved:
        raise CadError(
            f"{unresolved} {what} have no acceptable projection onto the CAD geometry (Newton "
            "and every fallback failed or landed farther than the local edge length); nothing "
            "was returned"
        )
    return pts, recs, report
