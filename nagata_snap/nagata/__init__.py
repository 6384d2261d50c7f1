"""Nagata mode: the geometry rebuilt from the mesh, no CAD needed.

* :mod:`~nagata_snap.nagata.patch` -- Nagata's (2005) quadratic curve and
  triangular patch from vertex positions and normals, and the closest point
  on them;
* :mod:`~nagata_snap.nagata.jets` -- vertex normals from a least-squares fit
  of the surface around each vertex, per smooth sector (the default);
* :mod:`~nagata_snap.nagata.normals` -- smooth sectors, creases and corners,
  and Neto's (2010) weighted-mean normals;
* :mod:`~nagata_snap.nagata.geometry` -- :class:`NagataGeometry`, the snapper's
  geometry built from the above.
"""

from nagata_snap.nagata.geometry import NagataGeometry
from nagata_snap.nagata.normals import NonManifoldError, NormalsError

__all__ = ["NagataGeometry", "NonManifoldError", "NormalsError"]
