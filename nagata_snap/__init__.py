"""nagata_snap: boundary snapping for DOLFINx adaptive refinement.

After ``dolfinx.mesh.refine``, new boundary vertices are placed on the true
geometry: the Nagata patch of their coarse parent facet (no CAD needed) or the
NURBS of an IGES file.  See :class:`Snapper`.
"""

# mpi4py must be imported before dolfinx/petsc4py with the PyPI wheels, or
# libmpi is not found.
import mpi4py.MPI  # noqa: F401

from nagata_snap.cad import CadError, CadGeometry
from nagata_snap.errors import MeshingError
from nagata_snap.mesh.lineage import LineageError
from nagata_snap.mesh.records import Records
from nagata_snap.nagata.geometry import NagataGeometry
from nagata_snap.nagata.normals import NonManifoldError, NormalsError
from nagata_snap.snapper import InvertedCellsError, Refined, Snapper, SnapReport

__all__ = [
    "NagataGeometry",
    "CadGeometry",
    "CadError",
    "Snapper",
    "Refined",
    "SnapReport",
    "Records",
    "InvertedCellsError",
    "LineageError",
    "MeshingError",
    "NonManifoldError",
    "NormalsError",
]

__version__ = "0.1.0"
