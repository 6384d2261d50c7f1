"""Inputs shared by tests/test_robustness.py and tests/mpi/bad_input.py (serial and MPI)."""

import numpy as np

import dolfinx.mesh


def exterior_tags(mesh, value=1):
    """Facet tags with ``value`` on every exterior facet."""
    fdim = mesh.topology.dim - 1
    mesh.topology.create_connectivity(fdim, mesh.topology.dim)
    f = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    return dolfinx.mesh.meshtags(mesh, fdim, f, np.full(len(f), value, dtype=np.int32))


def wall_tags(mesh, y0=0.0):
    """Tag 1 on the wall y = y0, tag 2 on the rest of the boundary."""
    mesh.topology.create_connectivity(1, 2)
    f = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    mid = dolfinx.mesh.compute_midpoints(mesh, 1, f)
    v = np.where(np.abs(mid[:, 1] - y0) < 1e-12, 1, 2).astype(np.int32)
    return dolfinx.mesh.meshtags(mesh, 1, f, v)


def wavy(deg):
    """Wall normals tilted by +-deg on alternate vertices: every second new midpoint
    is pushed into the domain by about 0.25 tan(deg) / 4 (more than a cell height)."""
    def f(x):
        s = np.where(np.round(x[:, 0] / 0.25) % 2 == 0, 1.0, -1.0)
        a = np.radians(deg) * s
        return np.c_[np.sin(a), -np.cos(a), 0 * a]
    return f


def flatten_one_cell(mesh):
    """Move a vertex of an owned interior triangle onto the midpoint of its other two.

    The triangle then has zero area (its other cells change shape too).
    """
    x, cells = mesh.geometry.x, mesh.geometry.dofmaps[0]
    nc = mesh.topology.index_map(2).size_local
    inner = (np.abs(x[:, :2] - 0.5) < 0.4).all(axis=1)
    v = cells[np.flatnonzero(inner[cells[:nc]].all(axis=1))[0]]
    x[v[0]] = 0.5 * (x[v[1]] + x[v[2]])
