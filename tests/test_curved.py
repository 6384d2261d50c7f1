"""Degree-2 geometry from the lineage: area/volume convergence orders, Jacobians, MPI."""

import os
import subprocess
import sys

import numpy as np
import pytest
import ufl
from mpi4py import MPI

import dolfinx.fem as fem
import generate
import make_iges

from nagata_snap import NagataGeometry, Snapper
from nagata_snap.cad import CadGeometry
from nagata_snap.curved import jacobian_determinants
from nagata_snap.cad.iges import write_iges
from nagata_snap.cad.nurbs import sphere

HERE = os.path.dirname(__file__)


def measure(m):
    form = fem.form(fem.Constant(m, 1.0) * ufl.dx(domain=m, metadata={"quadrature_degree": 8}))
    return m.comm.allreduce(fem.assemble_scalar(form))


def orders(errors):
    e = np.asarray(errors)
    return np.log2(e[:-1] / e[1:])


def test_dfg_area_order_straight_2_curved_4(tmp_path):
    md = generate.dfg_channel(MPI.COMM_WORLD, n_circle=16, h_far=0.1)
    mesh, ft = md.mesh, md.facet_tags
    geo = CadGeometry.from_iges(make_iges.write_dfg_circle(tmp_path))
    snapper = Snapper(mesh, ft, geo, tags=[generate.CYLINDER])
    exact = generate.DFG_LENGTH * generate.DFG_HEIGHT - np.pi * generate.DFG_RADIUS**2
    straight, curved = [], []
    for k in range(4):
        if k:
            mesh, ft, *_ = snapper.refine(mesh)
        cm, info = snapper.curved_mesh()
        assert cm.geometry.cmaps[0].degree == 2
        assert cm.topology is not None and cm.topology.index_map(2).size_global == mesh.topology.index_map(2).size_global
        assert info.reduced_midnodes == 0 and info.min_jacobian_ratio > 0.5
        straight.append(abs(measure(mesh) - exact))
        curved.append(abs(measure(cm) - exact))
    assert np.all(np.abs(orders(straight) - 2) < 0.1)
    assert np.all(orders(curved) > 3.5)
    assert curved[-1] < 1e-3 * straight[-1]


def test_ball_volume_order(tmp_path):
    path = tmp_path / "sphere.igs"
    write_iges(path, surfaces=[sphere((0.0, 0.0, 0.0), 1.0)])
    md = generate.ball(MPI.COMM_WORLD, radius=1.0, h=0.5)
    mesh, ft = md.mesh, md.facet_tags
    snapper = Snapper(mesh, ft, CadGeometry.from_iges(path), tags=[generate.BALL_SPHERE])
    exact = 4 / 3 * np.pi
    straight, curved = [], []
    for k in range(3):
        if k:
            mesh, ft, *_ = snapper.refine(mesh)
        cm, info = snapper.curved_mesh()
        assert info.min_jacobian_ratio > 0.0
        straight.append(abs(measure(mesh) - exact))
        curved.append(abs(measure(cm) - exact))
    assert abs(orders(straight)[-1] - 2) < 0.1  # (the first pair is pre-asymptotic: h = R / 2)
    assert np.all(orders(curved) >= 3.0)


def test_jacobian_guard_pulls_back_crushing_midnodes():
    """A mid-node pushed across its cell is moved back until det J > 0 everywhere."""
    md = generate.dfg_channel(MPI.COMM_WORLD, n_circle=8, boundary_layer=True)
    mesh, ft = md.mesh, md.facet_tags
    snapper = Snapper(mesh, ft, NagataGeometry(mesh, ft, tags=[generate.CYLINDER]))
    cm, info = snapper.curved_mesh(min_ratio=0.05)
    # the boundary layer's first cells are thinner than the 8-gon's sagitta: some are pulled back
    assert info.reduced_midnodes > 0
    assert info.min_jacobian_ratio >= 0.05
    tdim = 2
    cells = cm.geometry.dofmaps[0][: cm.topology.index_map(tdim).size_local]
    det = jacobian_determinants(cm.geometry.x, cells, tdim)
    assert np.all(np.sign(det) == np.sign(det[:, :1]))  # no sign change inside any cell


@pytest.mark.mpi
def test_curved_area_mpi_matches_serial(tmp_path):
    script = tmp_path / "curved_area.py"
    script.write_text(
        "import sys\n"
        f"sys.path[:0] = [{os.path.join(HERE, '..', 'meshes')!r}]\n"
        "import mpi4py.MPI as MPI, numpy as np, ufl, dolfinx.fem as fem, generate\n"
        "from nagata_snap import NagataGeometry, Snapper\n"
        "md = generate.dfg_channel(MPI.COMM_WORLD, n_circle=16, h_far=0.1)\n"
        "m, ft = md.mesh, md.facet_tags\n"
        "s = Snapper(m, ft, NagataGeometry(m, ft, tags=[generate.CYLINDER]))\n"
        "for k in range(2): m, ft, *_ = s.refine(m)\n"
        "cm, info = s.curved_mesh()\n"
        "f = fem.form(fem.Constant(cm, 1.0) * ufl.dx(domain=cm, metadata={'quadrature_degree': 8}))\n"
        "a = MPI.COMM_WORLD.allreduce(fem.assemble_scalar(f))\n"
        "if MPI.COMM_WORLD.rank == 0: print(repr(a), info.boundary_midnodes)\n"
    )
    outs = []
    for n in (1, 2):
        exe = [os.path.join(os.path.dirname(sys.executable), "mpiexec"), "-n", str(n)] if n > 1 else []
        r = subprocess.run(exe + [sys.executable, str(script)], capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        outs.append(r.stdout.split())
    assert outs[0][1] == outs[1][1]
    assert float(outs[0][0]) == pytest.approx(float(outs[1][0]), rel=1e-13)
