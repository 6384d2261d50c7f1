"""Fitted mode: a CAD-free surface of order ``p + 1`` from the coarse mesh.

* :mod:`~nagata_snap.fitted.fit` -- batched weighted least-squares height
  fits (surfaces) and offset fits (crease curves) around each vertex;
* :mod:`~nagata_snap.fitted.geometry` -- :class:`FittedGeometry`, the fits
  blended over the coarse facets (Jiao & Wang 2012), a
  :class:`~nagata_snap.geometry.SnapGeometry`.
"""

from nagata_snap.fitted.geometry import FittedGeometry

__all__ = ["FittedGeometry"]
