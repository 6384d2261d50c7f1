"""nagata_snap: boundary snapping for DOLFINx adaptive refinement.

After ``dolfinx.mesh.refine``, new boundary vertices are placed on the true
geometry: the Nagata patch of their coarse parent facet (no CAD needed) or the
NURBS of an IGES file.  See :class:`Snapper`.
"""

# mpi4py must be imported before dolfinx/petsc4py with the PyPI wheels, or
# libmpi is not found.
import mpi4py.MPI  # noqa: F401

from .cad import CadError, CadGeometry
from .geometry import NagataGeometry
from .hook import InvertedCellsError, Refined, Snapper, SnapReport
from .lineage import LineageError
from .normals import NonManifoldError, NormalsError
from .records import Records

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
    "NonManifoldError",
    "NormalsError",
]

__version__ = "0.1.0"
