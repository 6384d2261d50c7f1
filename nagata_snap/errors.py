"""The errors nagata_snap raises, in one module that every layer can import.

A foundation module (``nagata_snap.mesh``) raises the CAD mode's error as
well as the snapper does, so the classes live below all packages and import
nothing of the project.  Each is also importable from where it is raised
(``nagata_snap``, ``nagata_snap.cad``, ``nagata_snap.mesh.lineage``,
``nagata_snap.smoothing.repair``, ``nagata_snap.nagata.normals``): the
same class, so ``except`` clauses written against either name catch it.

(``nagata_snap.cad.read.ReadError`` stays in the reader: that module runs in
the reader process without the package, and its error becomes a
:class:`CadError` on the way back.)
"""

from __future__ import annotations

import sys

import numpy as np

__all__ = ["CadError", "MeshingError", "LineageError", "InvertedCellsError", "NormalsError",
           "NonManifoldError", "missing_extra"]


class CadError(RuntimeError):
    """The mesh boundary does not match the CAD geometry, or the CAD file cannot be used."""


class MeshingError(RuntimeError):
    """gmsh failed to mesh a CAD model (with every option tried).

    Attributes:
        sizes: the element sizes tried [length unit of the mesh], in order
            (empty where the error was raised on another process).
    """

    def __init__(self, message: str, sizes: tuple[float, ...] = ()):
        super().__init__(message)
        self.sizes = tuple(sizes)


class LineageError(RuntimeError):
    """The refined mesh is not a refinement of the previous level's mesh."""


class InvertedCellsError(RuntimeError):
    """Smoothing and repair could not produce a valid mesh.

    Attributes:
        cells: (m,) int64 global cell indices (``topology.index_map(tdim)``
            numbering) of the offending cells, identical on all ranks.
        count: global number of offending cells.
    """

    def __init__(self, message: str, cells: np.ndarray | None = None, count: int = 0):
        super().__init__(message)
        self.cells = np.asarray([] if cells is None else cells, dtype=np.int64)
        self.count = int(count)


class NormalsError(ValueError):
    """Normals that are zero, NaN, or opposite where they must agree."""


class NonManifoldError(ValueError):
    """A boundary ridge (2D vertex, 3D edge) shared by other than two boundary facets."""


def missing_extra(module: str, purpose: str) -> ImportError:
    """The error for an optional dependency of the ``cad`` extra that is not installed.

    Args:
        module: the module that failed to import (``"gmsh"``, ``"OCP"``).
        purpose: what needs it, completing "nagata_snap needs <module> <purpose>".

    Returns:
        An :class:`ImportError` whose message gives the install line for pip
        (PyPI wheels) and for conda-forge, to be raised ``from`` the original error.
    """
    package = {"OCP": "cadquery-ocp (module OCP)"}.get(module, module)
    return ImportError(
        f"nagata_snap needs {package} {purpose}, and it cannot be imported in this Python "
        f"({sys.executable}).  Install the CAD extra: pip install 'nagata_snap[cad]' "
        "(gmsh and cadquery-ocp from PyPI; in a conda environment the same pip line works, "
        "or conda install -c conda-forge gmsh python-gmsh ocp)."
    )
