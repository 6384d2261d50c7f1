"""The README: short, self-contained, and its Python examples run as written on files the user has.

The examples read ``part.step`` and ``mesh.msh`` from the working directory, as a user's
script would; the test writes both with gmsh (a plate with a through-hole, a ball cut out
of a box) into a temporary directory, runs each example there, then checks the mesh the
example ends with against the exact geometry of those files.
"""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
README = Path(ROOT, "README.md").read_text()
BLOCKS = re.findall(r"```(\w*)\n(.*?)```", README, flags=re.S)
PYTHON = [code for lang, code in BLOCKS if lang == "python"]

# the plate: [0, 40] x [0, 30] x [0, 10] mm minus a cylinder of radius 6 about (20, 15)
PLATE = (40.0, 30.0, 10.0, (20.0, 15.0), 6.0)
BALL_R = 0.5  # mesh.msh: the box [-1, 1]^3 minus the ball of radius 0.5 at the origin

MAKE_FILES = f"""
import gmsh
gmsh.initialize()
gmsh.option.setNumber("General.Terminal", 0)
L, W, H, (cx, cy), r = {PLATE!r}
gmsh.model.occ.addBox(0, 0, 0, L, W, H)
gmsh.model.occ.addCylinder(cx, cy, -1, 0, 0, H + 2, r)
gmsh.model.occ.cut([(3, 1)], [(3, 2)])
gmsh.model.occ.synchronize()
gmsh.write("part.step")
gmsh.clear()
gmsh.model.occ.addBox(-1, -1, -1, 2, 2, 2)
gmsh.model.occ.addSphere(0, 0, 0, {BALL_R})
gmsh.model.occ.cut([(3, 1)], [(3, 2)])
gmsh.model.occ.synchronize()
volumes = gmsh.model.getEntities(3)
gmsh.model.addPhysicalGroup(3, [v[1] for v in volumes], 1)
gmsh.model.addPhysicalGroup(2, [s[1] for s in gmsh.model.getBoundary(volumes, oriented=False)], 2)
gmsh.option.setNumber("Mesh.MeshSizeMax", 0.25)
gmsh.model.mesh.generate(3)
gmsh.write("mesh.msh")
gmsh.finalize()
"""

# appended to an example: the boundary vertices of the mesh it ended with
BOUNDARY = """
import numpy as _np
import dolfinx.mesh as _dm
_fdim = mesh.topology.dim - 1
mesh.topology.create_connectivity(_fdim, mesh.topology.dim)
_x = mesh.geometry.x[_np.unique(_dm.entities_to_geometry(mesh, _fdim, _dm.exterior_facet_indices(mesh.topology)))]
_np.save("boundary.npy", _x)
"""


def test_readme_is_short_and_self_contained():
    n = len(README.splitlines())
    assert n <= 250, f"README.md has {n} lines (at most 250: move details to docs/pages)"
    for lang, code in BLOCKS:
        bad = re.findall(r"^\s*(?:from|import)\s+(meshes|benchmarks)\b", code, flags=re.M)
        assert not bad, f"a README {lang or 'code'} block imports the repository's {bad[0]}/ (users do not have it)"
    for line in (b for _, code in BLOCKS for b in code.splitlines()):
        assert "meshes/" not in line and "benchmarks/" not in line, line
    assert "bash run.sh demo" in BLOCKS[0][1] and "bash run.sh test" in BLOCKS[0][1]  # set-up first
    assert all(len(code.splitlines()) <= 25 for code in PYTHON), "a README example is longer than 25 lines"


def test_readme_links_exist():
    """The check of ``bash run.sh check`` (docs/layout.py): length and links."""
    sys.path.insert(0, os.path.join(ROOT, "docs"))
    import layout

    assert layout.readme_problems(README) == []


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("readme")
    r = subprocess.run([sys.executable, "-c", MAKE_FILES], cwd=tmp, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return tmp


def run_example(code: str, workdir: Path):
    (workdir / "boundary.npy").unlink(missing_ok=True)
    script = workdir / "example.py"
    # the checkout, not an installed copy, as the other tests do
    script.write_text(f"import sys\nsys.path.insert(0, {ROOT!r})\n" + code + BOUNDARY)
    r = subprocess.run([sys.executable, str(script)], cwd=workdir, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, f"README example failed:\n{code}\n{r.stdout}\n{r.stderr}"
    import numpy as np

    return r.stdout, np.load(workdir / "boundary.npy")


def example(needle: str) -> str:
    found = [code for code in PYTHON if needle in code]
    assert len(found) == 1, f"README has {len(found)} python examples reading {needle}"
    return found[0]


def test_readme_step_example_snaps_onto_the_part(workdir):
    import numpy as np

    out, x = run_example(example('"part.step"'), workdir)
    assert "level 2" in out and "0 after" in out
    L, W, H, (cx, cy), r = PLATE
    planes = np.min(np.abs(np.stack([x[:, 0], x[:, 0] - L, x[:, 1], x[:, 1] - W, x[:, 2], x[:, 2] - H])), axis=0)
    hole = np.abs(np.hypot(x[:, 0] - cx, x[:, 1] - cy) - r)
    on_hole = hole < planes
    assert on_hole.sum() > 40  # the refined hole has many vertices (plain refinement: on chords) ...
    assert np.minimum(planes, hole).max() < 1e-9 * L  # ... and every boundary vertex is on the part
    assert (workdir / "refined.xdmf").exists()


def test_readme_msh_example_snaps_onto_the_ball(workdir):
    import numpy as np

    out, x = run_example(example('"mesh.msh"'), workdir)
    assert "level 2" in out
    radius = np.linalg.norm(x, axis=1)
    on_ball = radius < 0.9
    box = np.abs(np.abs(x[~on_ball]).max(axis=1) - 1.0)
    assert box.max() < 1e-12  # the box faces stay flat
    # Nagata patches of the coarse ball (h = 0.25): far closer than the chords' midpoints
    # (plain refinement: sagitta h^2 / (8 R) = 1.6e-2)
    assert np.abs(radius[on_ball] - BALL_R).max() < 3e-3
