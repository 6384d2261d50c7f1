"""The error classes live in ``nagata_snap.errors`` and are the same classes under their
older names (and where they are raised), so ``except`` clauses written against any of them
keep working."""

import importlib
import pathlib

import pytest

import nagata_snap
import nagata_snap.errors as errors

OLD_NAMES = {
    "CadError": ["nagata_snap", "nagata_snap.cad", "nagata_snap.cad.errors",
                 "nagata_snap.cad.geometry"],
    "LineageError": ["nagata_snap", "nagata_snap.mesh", "nagata_snap.mesh.lineage",
                     "nagata_snap.snapper"],
    "InvertedCellsError": ["nagata_snap", "nagata_snap.snapper", "nagata_snap.smoothing",
                           "nagata_snap.smoothing.repair"],
    "NormalsError": ["nagata_snap", "nagata_snap.nagata", "nagata_snap.nagata.normals"],
    "NonManifoldError": ["nagata_snap", "nagata_snap.nagata", "nagata_snap.nagata.normals"],
    "MeshingError": ["nagata_snap", "nagata_snap.meshing"],
}


@pytest.mark.parametrize("name", sorted(OLD_NAMES))
def test_one_class_under_every_name(name):
    cls = getattr(errors, name)
    assert name in errors.__all__
    for module in OLD_NAMES[name]:
        assert getattr(importlib.import_module(module), name) is cls, module
    assert name in nagata_snap.__all__


def test_errors_import_nothing_of_the_project():
    """The foundation of the layers: nagata_snap.errors imports no other module of the package."""
    src = pathlib.Path(errors.__file__).read_text()
    assert "from nagata_snap" not in src and "import nagata_snap" not in src


def test_caught_under_old_names():
    """Raised as the new class, caught by an ``except`` clause under the old name."""
    from nagata_snap.cad import CadError
    from nagata_snap.mesh.lineage import LineageError
    from nagata_snap.smoothing.repair import InvertedCellsError

    with pytest.raises(CadError):
        raise errors.CadError("x")
    with pytest.raises(LineageError):
        raise errors.LineageError("x")
    with pytest.raises(InvertedCellsError) as e:
        raise errors.InvertedCellsError("x", cells=[3, 1], count=2)
    assert e.value.cells.tolist() == [3, 1] and e.value.count == 2
