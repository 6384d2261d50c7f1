"""Mesh data the pipeline works on, independent of any geometry.

* :mod:`~nagata_snap.mesh.boundary` -- boundary facets of a DOLFINx mesh and
  their tags, facet normals, writing moved nodes back;
* :mod:`~nagata_snap.mesh.bisect` -- ``dolfinx.mesh.refine`` with ties among
  longest edges broken by position, so the cells do not depend on the partition;
* :mod:`~nagata_snap.mesh.lineage` -- parent maps of a refinement: which
  coarse facet or cell each new vertex came from, and where in it;
* :mod:`~nagata_snap.mesh.records` -- the per-vertex record (coarse facet,
  parametric position) carried from level to level;
* :mod:`~nagata_snap.mesh.simplex` -- kernels on simplices (edges, measures,
  normals, P1 gradients, barycentric coordinates), vectorised over all of them;
* :mod:`~nagata_snap.mesh.parallel` -- the MPI collectives the snapper uses.
"""

from nagata_snap.mesh.lineage import LineageError
from nagata_snap.mesh.records import Records

__all__ = ["LineageError", "Records"]
