"""Hard cases that invert cells when snapped without smoothing (issue: smoothing and guard).

2D: DFG channel with the cylinder as an 8-gon and a graded boundary layer
(first layer 4e-4, much thinner than the 8-gon's sagitta 3.8e-3).
3D: sphere in a box whose first cell layer off the sphere is squeezed to a
thin near-wall layer.  Without smoothing both raise InvertedCellsError; with
the default repair (linear band smoother, then the untangler on the
neighbourhood of the bad cells) no cell inverts, every vertex is on the
Nagata surface (none left short) and the changed cells keep at least a
third of the coarse mesh's smallest angle.  Machined-part features
(``hard_parts``), in CAD and Nagata mode: nothing left short, nothing
inverted, angles kept.
"""

import re

import numpy as np
import pytest
from mpi4py import MPI

import dolfinx.mesh
import generate
from surfaces import nagata_surface_error

from nagata_snap import InvertedCellsError, NagataGeometry, Snapper
from nagata_snap.smoothing.quality import quality_stats


def coarse_min_angle(mesh):
    return quality_stats(mesh.geometry.x, mesh.geometry.dofmaps[0], mesh.geometry.dim)["min_angle"].min()


def snapped_coords(mesh, ft, tag):
    nodes = np.unique(dolfinx.mesh.entities_to_geometry(mesh, mesh.topology.dim - 1, ft.find(tag)))
    return mesh.geometry.x[nodes]


def test_dfg_8gon_boundary_layer():
    md = generate.dfg_channel(MPI.COMM_WORLD, n_circle=8, boundary_layer=True)
    mesh, ft = md.mesh, md.facet_tags
    x0 = mesh.geometry.x.copy()
    geo = NagataGeometry(mesh, ft, tags=[generate.CYLINDER])
    with pytest.raises(InvertedCellsError, match="inverted"):
        Snapper(mesh, ft, geo, smoothing="none", repair=False).refine(mesh)
    assert np.array_equal(mesh.geometry.x, x0)  # the user's mesh is untouched

    R, n = generate.DFG_RADIUS, 8
    bound = R * (2 * np.pi / n) ** 4 / 128  # Nagata error of an n-gon with exact normals
    snapper = Snapper(mesh, ft, geo)
    amin0 = coarse_min_angle(mesh)
    m = mesh
    for level in range(3):
        m, f, *_, rep = snapper.refine(m)
        assert rep.inverted_before_smoothing > 0  # the case is hard at every level
        assert rep.inverted_after_smoothing == 0 and rep.partially_moved == 0
        assert rep.repair_stage == "untangle"  # the linear band smoother alone does not do it
        assert rep.quality.n_inverted_after == 0
        assert rep.quality.min_angle.min >= amin0 / 3
        ut = [a for a in rep.smoothing_attempts if a["stage"] == "untangle"]
        assert ut[-1]["n_bad"] == 0 and ut[-1]["cells"] < rep.num_cells / (2 if level == 0 else 8)
        x = snapped_coords(m, f, generate.CYLINDER)
        assert np.abs(np.hypot(x[:, 0] - 0.2, x[:, 1] - 0.2) - R).max() < 1.1 * bound
        assert "min angle" in str(rep.quality)  # printable table


def test_sphere_with_thin_wall_layer():
    md = generate.sphere_in_box(MPI.COMM_WORLD, h_sphere=0.25, h_box=0.5)
    mesh, ft = md.mesh, md.facet_tags
    generate.squeeze_wall_layer(mesh)
    geo = NagataGeometry(mesh, ft, tags=[generate.SPHERE])
    x0 = mesh.geometry.x.copy()
    with pytest.raises(InvertedCellsError):
        Snapper(mesh, ft, geo, smoothing="none", repair=False).refine(mesh)
    assert np.array_equal(mesh.geometry.x, x0)
    amin0 = coarse_min_angle(mesh)
    e_nagata = nagata_surface_error(geo, lambda x: np.abs(np.linalg.norm(x, axis=-1) - 0.5))
    snapper = Snapper(mesh, ft, geo)
    m = mesh
    for level in range(2):
        m, f, *_, rep = snapper.refine(m)
        if level == 0:
            assert rep.inverted_before_smoothing > 0
        # (before the untangler, two cells of the squeezed layer stayed inverted at
        # level 2 under every linear smoothing: 53 vertices were left short)
        assert rep.inverted_after_smoothing == 0 and rep.partially_moved == 0
        assert rep.quality.n_inverted_after == 0
        assert rep.quality.min_angle.min >= amin0 / 3
        # on the coarse Nagata surface: within its sampled distance from the sphere
        xs = snapped_coords(m, f, generate.SPHERE)
        assert np.abs(np.linalg.norm(xs, axis=1) - 0.5).max() <= e_nagata * (1 + 1e-9)


@pytest.mark.mpi
def test_hard_cases_mpi_same_repair_as_serial():
    """benchmarks/hard_cases.py under mpiexec -n 2: the same stages and counts as serially."""
    import os
    import subprocess
    import sys

    script = os.path.join(os.path.dirname(__file__), "..", "benchmarks", "hard_cases.py")
    mpiexec = os.path.join(os.path.dirname(sys.executable), "mpiexec")

    def rows(cmd):
        r = subprocess.run([*cmd, sys.executable, script, "--cases", "8gon-bl,sphere-squeezed"],
                           capture_output=True, text=True, timeout=900)
        assert r.returncode == 0, r.stdout + r.stderr
        assert "inverted_after 0" in r.stdout.splitlines()
        # level rows: level, cells, inverted before, stage, partial, short %, short/size, slid
        return [ln.split()[:8] for ln in r.stdout.splitlines()
                if re.fullmatch(r"\d+[um]", (ln.split() or [""])[0])]

    serial, par = rows([]), rows([mpiexec, "-n", "2"])
    assert len(serial) == 5 and serial == par


def test_partial_moves_are_the_last_resort_and_reported(capsys):
    """A hole touching a wall: its snapped midpoint would land on the wall.

    Untangling and sliding cannot help (no valid mesh has the vertex there);
    the repair leaves only the vertices at the contact short, by a reported
    amount, and says so in the report, its ``str`` and ``verbose`` output.
    """
    import hard_parts

    md = hard_parts.touching_hole(MPI.COMM_SELF)
    mesh, ft = md.mesh, md.facet_tags
    geo = NagataGeometry(mesh, ft, tags=[hard_parts.TOUCH_HOLE])
    m, f, *_, rep = Snapper(mesh, ft, geo, verbose=True).refine(mesh)
    stages = [a["stage"] for a in rep.smoothing_attempts]
    assert rep.repair_stage == "partial" and "untangle" in stages and "slide" in stages
    assert stages.index("partial") > stages.index("slide")  # the last resort
    assert 1 <= rep.partially_moved <= 5 and 0 < rep.max_shortfall < 1e-3
    assert rep.quality.n_inverted_after == 0 and rep.quality.n_shortfall == rep.partially_moved
    note = f"{rep.partially_moved} vertices left short of the geometry (max shortfall"
    assert note in str(rep) and note in capsys.readouterr().out
    # everything else is on the hole's Nagata curve; the short ones sit at the contact
    x = snapped_coords(m, f, hard_parts.TOUCH_HOLE)
    r = np.hypot(x[:, 0] - 0.5, x[:, 1] - 0.1)
    on = np.abs(r - 0.1) < 1e-3
    assert np.all(x[~on, 1] < 0.02) and np.count_nonzero(~on) <= rep.partially_moved
    assert np.all(x[:, 1] > 0)  # never through the wall


PARTS = ("plate", "thin_wall", "concave_cylinder", "reentrant_fillet")


def two_levels_nothing_short(mesh, ft, geo):
    """Two uniform levels: nothing short, nothing inverted, a third of the coarse min angle kept."""
    amin0 = coarse_min_angle(mesh)
    snapper = Snapper(mesh, ft, geo)
    m, reps = mesh, []
    for _ in range(2):
        m, *_, rep = snapper.refine(m)
        assert rep.partially_moved == 0 and rep.quality.n_inverted_after == 0
        assert rep.quality.min_angle.min >= amin0 / 3
        reps.append(rep)
    return reps


@pytest.mark.parametrize("name", PARTS)
def test_machined_part_cad_mode(name, tmp_path):
    """Machined-part features (plate with holes, counterbore, fillets and pocket; thin
    curved wall; concave cylinder; filleted re-entrant edge), snapped onto their own
    NURBS (IGES): every vertex on the CAD, nothing left short, no cell inverted,
    angles kept."""
    import warnings

    import hard_parts
    from nagata_snap.cad import CadGeometry

    path = hard_parts.write_iges(name, str(tmp_path / f"{name}.igs"))
    md = hard_parts.from_iges(MPI.COMM_SELF, path)
    mesh, ft = md.mesh, md.facet_tags
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # OCC's group entity (type 402)
        geo = CadGeometry.from_iges(path)
    for rep in two_levels_nothing_short(mesh, ft, geo):
        assert rep.geometry.n_unresolved == 0


@pytest.mark.parametrize("name", PARTS)
def test_machined_part_nagata_mode(name):
    """The same parts in Nagata mode (normals estimated from the coarse mesh, one tag
    per CAD face): no coarse patch folds (its normal never turns against the facet's),
    so every vertex reaches its patch, no cell inverts and the angles are kept."""
    import hard_parts

    md = hard_parts.part(MPI.COMM_SELF, name)
    mesh, ft = md.mesh, md.facet_tags
    geo = NagataGeometry(mesh, ft)
    assert hard_parts.folded_patches(geo) == 0
    two_levels_nothing_short(mesh, ft, geo)
