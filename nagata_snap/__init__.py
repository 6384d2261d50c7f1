"""nagata_snap: boundary snapping for DOLFINx adaptive refinement.

After ``dolfinx.mesh.refine``, new boundary vertices are placed on the true
geometry: the Nagata patch of their coarse parent facet (no CAD needed) or the
NURBS of an IGES file.  See :class:`Snapper`.
"""

DOLFINX_VERSION = (0, 11)
"""The DOLFINx release series (major, minor) this version of nagata_snap is written for."""

_INSTALL_DOLFINX = (
    "install DOLFINx {series} first, the way your environment gets it:\n"
    "  pip (PyPI wheel): pip install 'nagata_snap[wheel]'  (= pip install 'dolfinx-solver-real>={series},<{next}')\n"
    "  conda-forge:      conda install -c conda-forge 'fenics-dolfinx={series}' mpich\n"
    "  docker:           a DOLFINx {series} image, e.g. docker run -ti dolfinx/dolfinx:v{series}.0\n"
    "then pip install nagata_snap (without the [wheel] extra in conda and docker)"
)


def _check_dolfinx() -> None:
    """Raise ImportError naming what to install if DOLFINx is missing or of another release series.

    ``mpi4py.MPI`` is imported first: with the PyPI wheels it must precede
    dolfinx/petsc4py, or ``libmpi`` is not found.
    """
    series = ".".join(map(str, DOLFINX_VERSION))
    hint = _INSTALL_DOLFINX.format(series=series, next=f"{DOLFINX_VERSION[0]}.{DOLFINX_VERSION[1] + 1}")
    try:
        import mpi4py.MPI  # noqa: F401, I001  (before dolfinx)
        import dolfinx
    except ImportError as e:
        raise ImportError(f"nagata_snap needs DOLFINx {series} (with mpi4py and petsc4py), which cannot be "
                          f"imported here ({type(e).__name__}: {e});\n{hint}") from e
    found = str(getattr(dolfinx, "__version__", "unknown"))
    try:
        have = tuple(int(p) for p in found.split(".")[:2])
    except ValueError:
        have = ()
    if have != DOLFINX_VERSION:
        raise ImportError(f"nagata_snap {__version__} needs DOLFINx {series}.x, but DOLFINx {found} is installed "
                          f"(at {getattr(dolfinx, '__file__', '?')});\n{hint}")


__version__ = "0.1.0"
_check_dolfinx()

# after the check, so that a missing or wrong DOLFINx gives its message, not an import error deep inside
from nagata_snap.cad import CadError, CadGeometry  # noqa: E402
from nagata_snap.errors import MeshingError  # noqa: E402
from nagata_snap.fitted import FittedGeometry  # noqa: E402
from nagata_snap.mesh.lineage import LineageError  # noqa: E402
from nagata_snap.mesh.records import Records  # noqa: E402
from nagata_snap.nagata.geometry import NagataGeometry  # noqa: E402
from nagata_snap.nagata.normals import NonManifoldError, NormalsError  # noqa: E402
from nagata_snap.snapper import InvertedCellsError, Refined, Snapper, SnapReport  # noqa: E402

__all__ = [
    "NagataGeometry",
    "FittedGeometry",
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
