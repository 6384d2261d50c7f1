"""The ``nagata-snap`` command line (``python -m nagata_snap.cli``), run as a subprocess."""

import subprocess
import sys

import numpy as np
import pytest
from mpi4py import MPI

import dolfinx.io
import dolfinx.mesh
import generate
import make_iges

CENTRE = np.array(generate.DFG_CENTER)
R = generate.DFG_RADIUS


def cli(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "nagata_snap.cli", *map(str, args)],
        capture_output=True, text=True, timeout=300, cwd=cwd,
    )


@pytest.fixture(scope="module")
def msh(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "dfg_n16.msh"
    generate.dfg_channel(MPI.COMM_SELF, n_circle=16, h_far=0.1, msh_file=str(path))
    return path


def read_xdmf(path):
    with dolfinx.io.XDMFFile(MPI.COMM_SELF, str(path), "r") as f:
        mesh = f.read_mesh(name="mesh")
        mesh.topology.create_connectivity(mesh.topology.dim - 1, mesh.topology.dim)
        ft = f.read_meshtags(mesh, name="facet_tags")
    return mesh, ft


def cylinder_vertices(mesh, ft):
    nodes = dolfinx.mesh.entities_to_geometry(mesh, mesh.topology.dim - 1, ft.find(generate.CYLINDER))
    return mesh.geometry.x[np.unique(nodes)]


def circle_dist(x):
    return np.abs(np.hypot(x[:, 0] - CENTRE[0], x[:, 1] - CENTRE[1]) - R)


def test_level_line_states_vertices_left_short(tmp_path):
    """A vertex that cannot reach the geometry (a hole touching a wall) is reported on the level's line."""
    import hard_parts

    path = tmp_path / "touching.msh"
    hard_parts.touching_hole(MPI.COMM_SELF, msh_file=str(path))
    r = cli(path, "--tags", hard_parts.TOUCH_HOLE, "--levels", 1)
    assert r.returncode == 0, r.stdout + r.stderr
    line = next(ln for ln in r.stdout.splitlines() if "level 1/1" in ln)
    assert "vertices left short of the geometry (max shortfall" in line, line


def test_help():
    r = cli("--help")
    assert r.returncode == 0
    for opt in ("--tags", "--cad", "--iges", "--size", "--levels", "--crease-angle", "--output",
                "--plot", "--report", "--tag-key"):
        assert opt in r.stdout


@pytest.mark.parametrize("iges", [False, True])
def test_refine_msh_to_xdmf(msh, tmp_path, iges):
    out = tmp_path / "fine.xdmf"
    args = [msh, "--tags", generate.CYLINDER, "--levels", 2, "--output", out, "--report"]
    if iges:
        args += ["--iges", make_iges.write_dfg_circle(tmp_path)]
    r = cli(*args)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "nagata-snap: level 2/2" in r.stdout  # progress line
    assert "\n  level 2:" in r.stdout  # --report: the SnapReport of the level
    assert out.exists()
    mesh, ft = read_xdmf(out)
    coarse = generate.dfg_channel(MPI.COMM_SELF, n_circle=16, h_far=0.1).mesh
    assert mesh.geometry.dim == 2
    assert mesh.topology.index_map(2).size_global == 16 * coarse.topology.index_map(2).size_global
    assert sorted(np.unique(ft.values)) == [1, 2, 3, 4]
    x = cylinder_vertices(mesh, ft)
    assert len(x) == 16 * 4  # the 16-gon's edges bisected twice
    # exact NURBS circle / Nagata curve of a 16-gon (R (2 pi/16)^4 / 128 = 9.3e-6);
    # the coarse polygon is 9.6e-4 away from the circle at its edge midpoints
    tol = 1e-12 if iges else 1e-4
    assert circle_dist(x).max() < tol


def test_xdmf_and_meshio_inputs(msh, tmp_path):
    # the CLI's own XDMF output is a valid input
    out1 = tmp_path / "l1.xdmf"
    assert cli(msh, "--tags", 4, "--output", out1).returncode == 0
    out2 = tmp_path / "l2.xdmf"
    r = cli(out1, "--tags", 4, "--output", out2)
    assert r.returncode == 0, r.stderr
    # a meshio format (VTU) with the tags in cell data 'gmsh:physical'
    import meshio

    m = meshio.read(msh)
    vtu = tmp_path / "coarse.vtu"
    meshio.Mesh(m.points, m.cells, cell_data={"ref": m.cell_data["gmsh:physical"]}).write(vtu)
    r = cli(vtu, "--tags", 4, "--levels", 2, "--output", tmp_path / "v.xdmf")
    assert r.returncode == 2 and "--tag-key" in r.stderr and "ref" in r.stderr
    r = cli(vtu, "--tags", 4, "--levels", 2, "--tag-key", "ref", "--output", tmp_path / "v.xdmf")
    assert r.returncode == 0, r.stderr
    for path in (out2, tmp_path / "v.xdmf"):
        mesh, ft = read_xdmf(path)
        assert circle_dist(cylinder_vertices(mesh, ft)).max() < 1e-4


def test_bp_output(msh, tmp_path):
    out = tmp_path / "fine.bp"
    r = cli(msh, "--tags", 4, "--output", out)
    assert r.returncode == 0, r.stderr
    assert out.is_dir() and any(out.iterdir())


@pytest.mark.parametrize(
    "content, message",
    [("this is not a mesh\n", "cannot read"), (None, "does not exist")],
)
def test_bad_file(tmp_path, content, message):
    path = tmp_path / "bad.msh"
    if content is not None:
        path.write_text(content)
    r = cli(path, "--tags", 4)
    assert r.returncode == 2
    assert r.stderr.startswith("nagata-snap: error:") and message in r.stderr
    assert "Traceback" not in r.stderr


def test_unknown_tag(msh):
    r = cli(msh, "--tags", 4, 7)
    assert r.returncode == 2
    assert "nagata-snap: error:" in r.stderr and "7" in r.stderr
    assert "available facet tags: 1, 2, 3, 4" in r.stderr
    assert "Traceback" not in r.stderr


def test_bad_options(msh, tmp_path):
    r = cli(msh, "--tags", 4, "--output", tmp_path / "x.vtk")
    assert r.returncode == 2 and ".xdmf or .bp" in r.stderr
    r = cli(msh, "--tags", 4, "--iges", tmp_path / "missing.igs")
    assert r.returncode == 2 and "does not exist" in r.stderr
    r = cli(msh, "--tags", 4, "--iges", msh)  # not a CAD file
    assert r.returncode == 2 and "cannot use the CAD file" in r.stderr and "Traceback" not in r.stderr
    r = cli(msh)  # --tags is required for a mesh
    assert r.returncode == 2 and "--tags" in r.stderr
    r = cli(msh, "--tags", 4, "--size", 0.1)  # --size is for CAD inputs
    assert r.returncode == 2 and "--size applies to a CAD input" in r.stderr
    r = cli(msh, "--tags", 4, "--plot", tmp_path / "x.pdf")
    assert r.returncode == 2 and "--plot must end in .png" in r.stderr


# ----------------------------------------------------------------------
# CAD input: meshed by gmsh, snapped onto its own faces
# ----------------------------------------------------------------------
@pytest.fixture(scope="module")
def step(tmp_path_factory):
    import parts

    return parts.write_part("box_fillet_chamfer", tmp_path_factory.mktemp("part"), ("step",))["step"]


def test_cad_input_to_xdmf_with_plot(step, tmp_path):
    out, png = tmp_path / "box.xdmf", tmp_path / "levels.png"
    r = cli(step, "--size", 20, "--curvature", 4, "--levels", 2, "-o", out, "--plot", png)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "meshed" in r.stdout and "18 faces" in r.stdout
    assert "nagata-snap: level 2/2" in r.stdout
    summary = [line for line in r.stdout.splitlines() if "summary" in line]
    assert len(summary) == 1 and "0 boundary vertices left short" in summary[0]
    d = float(summary[0].split("from its CAD face ")[1].split()[0])
    assert d <= 1e-9 * 75  # model size ~75 mm
    assert out.exists() and png.exists() and png.stat().st_size > 10_000
    mesh, ft = read_xdmf(out)
    assert mesh.topology.index_map(3).size_global > 64 * 300 and len(np.unique(ft.values)) == 18
    assert_only_our_lines(r.stdout + r.stderr)


def assert_only_our_lines(text):
    """Every line printed is the command's own: none of gmsh's or OpenCASCADE's console output."""
    lines = text.splitlines()
    assert lines and all(line.startswith("nagata-snap: ") for line in lines), text
    for foreign in ("Info", "Warning :", "*****", "Error :"):
        assert foreign not in text, text


def test_iges_input_prints_only_its_lines(tmp_path):
    """OpenCASCADE's IGES reader prints entity counts unless silenced; gmsh logs its import."""
    import parts

    iges = parts.write_part("box_fillet_chamfer", tmp_path, ("iges",))["iges"]
    r = cli(iges, "--size", 20, "--curvature", 4, "--levels", 1)
    assert r.returncode == 0, r.stdout + r.stderr
    assert_only_our_lines(r.stdout + r.stderr)


OVERLAP = "Invalid boundary mesh (overlapping facets) on surface 3 surface 7"


def _fail_3d(monkeypatch, fail):
    """gmsh's 3D meshing raises its overlapping-facets error on the calls ``fail(k)`` picks."""
    import gmsh

    real, calls = gmsh.model.mesh.generate, [0]

    def generate(dim=3):
        if dim == 3:
            calls[0] += 1
            if fail(calls[0] - 1):
                raise Exception(OVERLAP)
        return real(dim)

    monkeypatch.setattr(gmsh.model.mesh, "generate", generate)


def test_cad_input_retries_when_gmsh_fails(step, monkeypatch, capfd):
    """In this process, gmsh failing once: the command says what failed and what it retries,
    snaps the retried mesh, and nothing but its own lines reaches the terminal (file
    descriptors 1 and 2, so also the reader process and gmsh's C++ output)."""
    from nagata_snap import cli as cli_module

    _fail_3d(monkeypatch, lambda k: k == 0)
    rc = cli_module.main([str(step), "--size", "20", "--curvature", "4", "--levels", "1"])
    out, err = capfd.readouterr()
    assert rc == 0, out + err
    retry = [line for line in out.splitlines() if "retrying" in line]
    assert len(retry) == 1 and OVERLAP in retry[0] and "with the options asked for (size 20)" in retry[0]
    assert retry[0].endswith("retrying with 0.5 x the element size")
    assert "(size 10 MM, 0.5 x the element size)" in out
    assert "0 boundary vertices left short" in out
    assert_only_our_lines(out + err)


def test_cad_input_every_retry_fails(step, monkeypatch, capfd):
    """gmsh failing every time: exit 2, an error naming gmsh's failure and the flags to try."""
    from nagata_snap import cli as cli_module

    _fail_3d(monkeypatch, lambda k: True)
    rc = cli_module.main([str(step), "--size", "20", "--curvature", "4", "--levels", "1"])
    out, err = capfd.readouterr()
    assert rc == 2
    assert err.startswith("nagata-snap: error: ") and OVERLAP in err and "gmsh could not mesh" in err
    assert "next, try --size 5 (or smaller), or --curvature 0" in err
    assert f"--cad {step}" in err
    assert out.count("retrying with") == 4
    assert_only_our_lines(out + err)


def test_cad_input_errors(step, tmp_path):
    r = cli(tmp_path / "missing.step", "--levels", 1)
    assert r.returncode == 2 and "does not exist" in r.stderr
    bad = tmp_path / "bad.step"
    bad.write_text("not a step file\n")
    r = cli(bad, "--levels", 1)
    assert r.returncode == 2 and "nagata-snap: error:" in r.stderr and "Traceback" not in r.stderr
    r = cli(step, "--cad", step)
    assert r.returncode == 2 and "--cad applies to a mesh input" in r.stderr
    r = cli(step, "--size", -1)
    assert r.returncode == 2 and "--size must be positive" in r.stderr


def test_heartbeat_names_the_stage(monkeypatch):
    """The heartbeat's lines say how long the level has run and which stage it is in."""
    import time
    from types import SimpleNamespace

    from nagata_snap import cli as cli_module

    monkeypatch.setattr(cli_module, "HEARTBEAT", 0.02)
    lines, snapper = [], SimpleNamespace(stage="place")
    with cli_module._Heartbeat(lines.append, 3, snapper):
        time.sleep(0.1)
        snapper.stage = None
        time.sleep(0.1)
    assert any("level 3: still running" in t and "placing the new boundary vertices" in t for t in lines), lines
    assert lines[-1].endswith(" s)"), lines  # no stage named between stages


def test_tag_lists_are_ranges():
    from nagata_snap.cli import tag_list

    assert tag_list(range(1, 276)) == "1-275"
    assert tag_list([7, 1, 2, 3, 9, 10]) == "1-3, 7, 9, 10"
    assert tag_list([]) == "none"


def test_distance_histogram_shows_a_few_hundred_vertices_off_the_cad():
    """--plot: the count axes are logarithmic, so 300 vertices at 1e-6 of the size show as a
    bar next to a million on the CAD (on a linear axis they would be 0.03 % of its height)."""
    from types import SimpleNamespace

    import matplotlib.pyplot as plt

    from nagata_snap.cli import level_figure

    size = 100.0
    dist = np.concatenate([np.full(1_000_000, 1e-15 * size), np.full(300, 1e-6 * size)])
    fig = level_figure([(1, SimpleNamespace(quality=None), dist)], SimpleNamespace(size=size))
    try:
        ax = fig.axes[2]
        assert ax.get_yscale() == "log"
        heights = sorted(p.get_height() for p in ax.patches if p.get_height() > 0)
        assert heights == [300, 1_000_000]
        low, high = ax.get_ylim()
        # the small bar reaches past the middle of the axis (in decades): visible
        assert (np.log10(300) - np.log10(low)) / (np.log10(high) - np.log10(low)) > 0.4
    finally:
        plt.close(fig)
