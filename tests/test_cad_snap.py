"""CAD-mode snapping loops: DFG cylinder from an IGES circle, Kadir's 3D cylinder.

The loops run through ``tests/mpi/snap_loop.py`` (serial and ``mpiexec -n 2``);
vertices are checked against the exact circle/cylinder the NURBS represent.
In 3D, DOLFINx's marked refinement chooses which extra edges to bisect in a
partition-dependent way, so 3D adaptive runs are compared over one level and
3D uniform runs (whose boundary vertex set is fixed) over two.
"""

import os
import subprocess
import sys

import gmsh
import numpy as np
import pytest
from scipy.spatial import cKDTree

import generate

HERE = os.path.dirname(__file__)


def run(n, args, tmp_path):
    out = tmp_path / f"{args[0]}_np{n}.npz"
    exe = [os.path.join(os.path.dirname(sys.executable), "mpiexec"), "-n", str(n)] if n > 1 else []
    r = subprocess.run(
        [*exe, sys.executable, os.path.join(HERE, "mpi", "snap_loop.py"), *args, str(out)],
        capture_output=True, text=True, timeout=900,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    return np.load(out)


def circle_dist(x):
    return np.abs(np.hypot(x[:, 0] - 0.2, x[:, 1] - 0.2) - generate.DFG_RADIUS)


def cyl_dist(x):
    cx, cy = generate.KADIR_CYL_CENTER
    return np.abs(np.hypot(x[:, 0] - cx, x[:, 1] - cy) - generate.KADIR_CYL_RADIUS)


@pytest.mark.mpi
@pytest.mark.parametrize(
    "case, mode, levels, dist, size",
    [("dfg_iges", "uniform", 4, circle_dist, 2.2), ("dfg_iges", "adaptive", 3, circle_dist, 2.2),
     ("cylinder_iges", "uniform", 2, cyl_dist, 1.1), ("cylinder_iges", "adaptive", 1, cyl_dist, 1.1)],
)
def test_cad_loop_on_exact_geometry_serial_and_mpi(case, mode, levels, dist, size, tmp_path):
    serial = run(1, [case, str(levels), mode], tmp_path)
    par = run(2, [case, str(levels), mode], tmp_path)
    nsnapped = 0
    for k in range(1, levels + 1):
        s = serial[f"snapped{k}"]
        assert len(s) > nsnapped  # refinement adds vertices on the curved boundary
        nsnapped = len(s)
        assert dist(s).max() <= 1e-12 * size
        hist = serial[f"iterations{k}"]
        assert len(hist) - 1 <= 7  # Kadir Table 4.2: at most 7 seeded Newton iterations
        for key in (f"snapped{k}", f"boundary{k}"):
            a, b = serial[key], par[key]
            assert a.shape == b.shape
            d, i = cKDTree(a).query(b)
            assert d.max() <= 1e-12 * size
            assert np.unique(i).size == len(i)  # one to one: no point matched twice, none missed


def test_kadir_cylinder_file_snapping_matches_occ(tmp_path):
    """Kadir's printed cylinder (weights rounded to 0.707107) against OpenCASCADE's closest point."""
    from mpi4py import MPI

    from nagata_snap import Snapper
    from nagata_snap.cad import CadGeometry

    path = os.path.join(generate._MESHES_DIR, "kadir_cylinder.igs")
    md = generate.cylinder_in_box(MPI.COMM_WORLD, h_cylinder=0.03, h_box=0.15)
    mesh, ft = md.mesh, md.facet_tags
    geo = CadGeometry.from_iges(path)  # in the file's own unit (inches), as the mesh
    snapper = Snapper(mesh, ft, geo, tags=[generate.CIB_CYLINDER])
    mesh, ft, *_ , report = snapper.refine(mesh)
    import dolfinx.mesh

    nodes = np.unique(dolfinx.mesh.entities_to_geometry(mesh, 2, ft.find(generate.CIB_CYLINDER)))
    x = mesh.geometry.x[nodes]
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.occ.importShapes(path)  # OCC converts the file's inches to mm
        gmsh.model.occ.synchronize()
        (dim, tag), = gmsh.model.getEntities(2)
        cp = np.asarray(gmsh.model.getClosestPoint(dim, tag, 25.4 * x.ravel())[0]).reshape(-1, 3) / 25.4
    finally:
        gmsh.finalize()
    interior = (x[:, 2] > 1e-6) & (x[:, 2] < 0.4 - 1e-6)  # OCC is ~1e-9 off at face ends
    assert np.linalg.norm(cp - x, axis=1)[interior].max() <= 1e-9 * 1.1
    assert report.geometry.n_unresolved == 0
    assert len(report.geometry.iterations_histogram) - 1 <= 7
