"""What a user sees when DOLFINx is missing or of another release, and what the package needs at import.

Each case runs ``import nagata_snap`` in a fresh interpreter whose ``dolfinx`` is hidden
(``sys.modules["dolfinx"] = None``, as if it were not installed) or replaced by a module of
another version, before the package is imported.
"""

import os
import subprocess
import sys
import tomllib

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def import_with(prelude: str) -> subprocess.CompletedProcess:
    code = f"import sys\nsys.path.insert(0, {ROOT!r})\n{prelude}\nimport nagata_snap\n"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_missing_dolfinx_says_what_to_install():
    r = import_with("sys.modules['dolfinx'] = None")
    assert r.returncode != 0
    last = r.stderr[r.stderr.rindex("ImportError"):]
    assert "nagata_snap needs DOLFINx 0.11" in last and "cannot be imported" in last
    # one install line per environment
    assert "pip install 'nagata_snap[wheel]'" in last
    assert "conda install -c conda-forge 'fenics-dolfinx=0.11'" in last
    assert "docker run" in last and "dolfinx/dolfinx:v0.11" in last


def test_missing_mpi4py_says_what_to_install():
    r = import_with("sys.modules['mpi4py'] = None")
    assert r.returncode != 0 and "nagata_snap needs DOLFINx 0.11" in r.stderr and "mpi4py" in r.stderr


@pytest.mark.parametrize("version", ["0.10.0", "0.12.1", "1.0.0"])
def test_wrong_dolfinx_version_says_which_is_needed(version):
    fake = f"import types\nm = types.ModuleType('dolfinx')\nm.__version__ = {version!r}\nsys.modules['dolfinx'] = m"
    r = import_with(fake)
    assert r.returncode != 0
    assert f"needs DOLFINx 0.11.x, but DOLFINx {version} is installed" in r.stderr
    assert "pip install 'nagata_snap[wheel]'" in r.stderr


def test_installed_dolfinx_passes_the_check():
    import dolfinx

    import nagata_snap

    assert tuple(int(p) for p in dolfinx.__version__.split(".")[:2]) == nagata_snap.DOLFINX_VERSION


def test_import_needs_neither_gmsh_nor_occ():
    """gmsh and OCP are extras (`cad`): `import nagata_snap` works without them."""
    r = import_with("sys.modules['gmsh'] = None\nsys.modules['OCP'] = None")
    assert r.returncode == 0, r.stderr


def test_dependencies_match_what_import_needs():
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as f:
        meta = tomllib.load(f)["project"]
    names = {d.split(">")[0].split("=")[0].split("<")[0].strip() for d in meta["dependencies"]}
    # DOLFINx, gmsh and OpenCASCADE are not hard dependencies (see docs/pages/install.md) ...
    assert not names & {"dolfinx-solver-real", "fenics-dolfinx", "gmsh", "cadquery-ocp"}
    extras = meta["optional-dependencies"]
    # ... but the extras bring them
    assert any(d.startswith("dolfinx-solver-real") for d in extras["wheel"])
    assert {d.split(">")[0] for d in extras["cad"]} == {"gmsh", "cadquery-ocp"}


def _hide_cad_extra(tmp_path) -> dict:
    """An environment whose ``gmsh`` and ``OCP`` fail to import (in child processes too)."""
    (tmp_path / "OCP").mkdir()
    (tmp_path / "OCP" / "__init__.py").write_text("raise ImportError('No module named OCP')\n")
    (tmp_path / "gmsh.py").write_text("raise ImportError('No module named gmsh')\n")
    return dict(os.environ, PYTHONPATH=f"{tmp_path}{os.pathsep}{ROOT}")


CORPUS_STEP = os.path.join(ROOT, "meshes", "corpus", "bolt_catia_v5_cax_if.stp")


def test_cli_without_the_cad_extra_says_what_to_install(tmp_path):
    """The CLI on a STEP file without gmsh: an error line with the install command, exit 2."""
    r = subprocess.run([sys.executable, "-m", "nagata_snap.cli", CORPUS_STEP, "--levels", "1"],
                       capture_output=True, text=True, timeout=300, env=_hide_cad_extra(tmp_path))
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert "needs gmsh" in r.stderr and "pip install 'nagata_snap[cad]'" in r.stderr


def test_cad_read_without_occ_says_what_to_install(tmp_path):
    """CadGeometry.from_file without OpenCASCADE: a CadError with the install command."""
    code = ("import mpi4py.MPI\nimport nagata_snap\n"
            "try:\n"
            f"    nagata_snap.CadGeometry.from_file({CORPUS_STEP!r})\n"
            "except nagata_snap.CadError as e:\n"
            "    print('CadError:', e)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                       env=_hide_cad_extra(tmp_path))
    assert r.returncode == 0, r.stderr
    assert "CadError:" in r.stdout and "OCP" in r.stdout
    assert "pip install 'nagata_snap[cad]'" in r.stdout
