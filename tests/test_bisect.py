"""Refinement with ties among longest edges broken by position (:mod:`nagata_snap.mesh.bisect`).

The truth is DOLFINx itself: the refined vertices are exactly the coarse vertices
and ``dolfinx.mesh.compute_midpoints`` of the coarse edges (bit for bit), the
coarse mesh is left bit for bit as it was, and the cells are the same serially
and under ``mpiexec -n 2`` and ``-n 3``, where plain ``dolfinx.mesh.refine``
splits some faces otherwise.
"""

import os
import subprocess
import sys

import mpi4py.MPI as MPI
import numpy as np
import pytest

import dolfinx.mesh

from nagata_snap.mesh import bisect

HERE = os.path.dirname(os.path.abspath(__file__))
COMM = MPI.COMM_WORLD


def cylinder_mesh(comm: MPI.Comm, size: float = 0.3) -> dolfinx.mesh.Mesh:
    """gmsh tetrahedra of the cylinder of radius 0.5 and height 1 (rank 0 meshes)."""
    import gmsh

    from dolfinx.io import gmsh as dgmsh

    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        if comm.rank == 0:
            gmsh.model.occ.addCylinder(0, 0, 0, 0, 0, 1, 0.5)
            gmsh.model.occ.synchronize()
            gmsh.model.addPhysicalGroup(3, [1], 1)
            gmsh.option.setNumber("Mesh.MeshSizeMax", size)
            gmsh.model.mesh.generate(3)
        return dgmsh.model_to_mesh(gmsh.model, comm, 0, gdim=3)[0]
    finally:
        gmsh.finalize()


def sorted_cells(mesh: dolfinx.mesh.Mesh) -> np.ndarray:
    """``(owned cells, 3 * nv)``: each owned cell as its vertex positions in lexicographic order."""
    n = mesh.topology.index_map(mesh.topology.dim).size_local
    X = mesh.geometry.x[mesh.geometry.dofmaps[0][:n]]
    rows = [np.ascontiguousarray(X[:, :, k]) for k in range(3)]
    order = np.lexsort(rows[::-1], axis=1)
    return np.take_along_axis(X, order[:, :, None], axis=1).reshape(n, -1)


def _as_set(points: np.ndarray) -> set[bytes]:
    return {row.tobytes() for row in np.ascontiguousarray(points)}


def _check_refinement(mesh0: dolfinx.mesh.Mesh, edges: np.ndarray | None) -> None:
    """The coarse mesh is unchanged and every refined vertex is a coarse vertex or a coarse edge's
    midpoint as DOLFINx computes it, bit for bit; uniform refinement has all of them."""
    x0 = mesh0.geometry.x.copy()
    mesh0.topology.create_entities(1)
    mesh0.topology.create_connectivity(1, mesh0.topology.dim)
    mesh1, parent_cell, parent_facet = bisect.refine(mesh0, edges)
    assert np.array_equal(mesh0.geometry.x.view(np.uint64), x0.view(np.uint64))
    ne = mesh0.topology.index_map(1).size_local + mesh0.topology.index_map(1).num_ghosts
    mids = dolfinx.mesh.compute_midpoints(mesh0, 1, np.arange(ne, dtype=np.int32))
    truth = _as_set(np.concatenate([x0, mids]))
    got = _as_set(mesh1.geometry.x)
    assert got <= truth
    if edges is None:
        assert len(got) == len(truth)
    n1 = mesh1.topology.index_map(mesh1.topology.dim).size_local
    assert len(parent_cell) == n1 and len(parent_facet) == n1 * (mesh1.topology.dim + 1)


@pytest.mark.parametrize("marked", [False, True])
def test_vertices_are_dolfinx_midpoints_3d(marked):
    mesh = cylinder_mesh(COMM)
    edges = None
    if marked:
        mesh.topology.create_entities(1)
        mesh.topology.create_connectivity(1, 3)
        mid = dolfinx.mesh.compute_midpoints(
            mesh, 1, np.arange(mesh.topology.index_map(1).size_local, dtype=np.int32))
        edges = np.flatnonzero(mid[:, 2] < 0.3).astype(np.int32)
    _check_refinement(mesh, edges)


def test_planar_mesh_keeps_zero_z():
    """A 2D mesh (structured: ties everywhere) keeps z = 0 exactly and DOLFINx's midpoints."""
    mesh = dolfinx.mesh.create_unit_square(COMM, 5, 7)
    _check_refinement(mesh, None)
    mesh1 = bisect.refine(mesh, None)[0]
    assert np.all(mesh1.geometry.x[:, 2] == 0.0)


def test_jitter_is_an_involution():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(1000, 3)) * 10.0 ** rng.integers(-6, 6, size=(1000, 1))
    y = x.copy()
    bisect.jitter(y, 3)
    assert np.mean(y != x) > 0.99  # 1/256 of the coordinates keep their bits
    assert np.all(np.abs(y - x) <= 2.0 ** (bisect.JITTER_BITS - 52) * np.abs(x))
    bisect.jitter(y, 3)
    assert np.array_equal(y.view(np.uint64), x.view(np.uint64))


@pytest.mark.mpi
def test_cells_do_not_depend_on_the_partition(tmp_path):
    """Two uniform refinements of a gmsh cylinder: the same cells serially, under ``-n 2`` and
    ``-n 3``; plain ``dolfinx.mesh.refine`` splits some otherwise under ``-n 2`` (ties broken by
    partition-dependent vertex numbers), which is what makes the check meaningful."""
    mpiexec = os.path.join(os.path.dirname(sys.executable), "mpiexec")
    script = os.path.join(HERE, "mpi", "bisect_cells.py")
    cells = {}
    for how, procs in (("bisect", 1), ("bisect", 2), ("bisect", 3), ("plain", 1), ("plain", 2)):
        out = str(tmp_path / f"{how}{procs}.npy")
        cmd = [sys.executable, script, how, out]
        r = subprocess.run(cmd if procs == 1 else [mpiexec, "-n", str(procs), *cmd],
                           capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stdout + r.stderr
        cells[how, procs] = np.load(out)
    serial = cells["bisect", 1]
    for procs in (2, 3):
        assert np.array_equal(cells["bisect", procs], serial), procs
    plain = _as_set(cells["plain", 1])
    assert len(plain - _as_set(cells["plain", 2])) > 0, (
        "plain dolfinx.mesh.refine gave the same cells under -n 2: the test mesh no longer has "
        "ties that DOLFINx breaks by partition (or DOLFINx now breaks them by position)")
