"""Lineage records: where each boundary-facet vertex sits on the geometry.

Every snapped boundary facet of every refinement level is known by a
*record*: the geometric entity it lies in (``root``) and the parameters of
each of its vertices on that entity (``params``).

* Nagata mode: ``root`` is the coarse boundary facet (an index into the
  patches of :class:`nagata_snap.nagata.geometry.NagataGeometry`) and ``params``
  are barycentric coordinates in that coarse facet, shape ``(nf, nfv, nfv)``.
* CAD mode: ``root`` is the CAD face (2D: edge curve) and ``params`` are
  its ``(u, v)`` (``(u,)``) parameters, unwrapped per facet across periodic
  seams; with a CAD model's topology (3D) three more channels per vertex
  mark the facet's coarse edges that lie on CAD edges (see
  :mod:`nagata_snap.cad.geometry`): shape ``(nf, nfv, 1 | 2 | 5)``.

Refinement never needs to know which mode is in use: a child facet's record
is the parent's ``root`` and the barycentric combination of the parent's
``params`` (see :func:`refine_records`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["Records", "refine_records"]


@dataclass
class Records:
    """Per-facet lineage records.

    Attributes:
        root: ``(nf,)`` int64, entity (coarse facet or NURBS patch) of each facet.
        params: ``(nf, nfv, k)`` float64, parameters of each facet vertex on ``root``.
    """

    root: npt.NDArray[np.int64]
    params: npt.NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.root.shape[0])

    def take(self, index: npt.ArrayLike) -> Records:
        """Records of a subset of facets, ``index`` into the facet axis."""
        index = np.asarray(index)
        return Records(self.root[index], self.params[index])


def refine_records(
    parent: Records, which: npt.NDArray[np.int64], weights: npt.NDArray[np.float64]
) -> Records:
    """Records of child facets from their parent facets' records.

    Args:
        parent: records of the parent level.
        which: ``(nc,)`` index of each child's parent facet into ``parent``.
        weights: ``(nc, nfv, nfv)`` barycentric coordinates of each child
            vertex in its parent facet (rows sum to one; entries are 0, 1/2
            or 1 for edge bisection, so the combination is exact in binary
            floating point and records never drift).

    Returns:
        Child records: same ``root`` as the parent, ``params = weights @ params``.
    """
    return Records(
        parent.root[which],
        np.einsum("cij,cjk->cik", weights, parent.params[which]),
    )
