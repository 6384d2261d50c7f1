"""Lineage of facets through refinement, checked against DOLFINx itself.

The snapper finds the exterior (and tagged interface) facets of each refined
mesh from cell-local facets, without creating facet entities.  Here the
facet tags it returns must equal ``dolfinx.mesh.transfer_meshtag`` of the
previous tags (DOLFINx's own transfer through ``parent_cell`` /
``parent_facet``), its boundary must equal ``exterior_facet_indices``, and
the barycentric weights must reproduce the child vertices from the parent's.
A refined mesh that does not tile the previous level's boundary is refused.
"""

import mpi4py.MPI as MPI
import numpy as np
import pytest

import dolfinx.mesh

import generate
from nagata_snap import LineageError, NagataGeometry, Snapper
from nagata_snap.mesh.boundary import boundary_facets
from nagata_snap.mesh.lineage import child_facets

COMM = MPI.COMM_WORLD


def _tag_interface(mesh, ft, value, n):
    """Add tag ``value`` to ``n`` interior facets (an interface that is not snapped)."""
    fdim = mesh.topology.dim - 1
    mesh.topology.create_connectivity(fdim, mesh.topology.dim)
    f2c = mesh.topology.connectivity(fdim, mesh.topology.dim)
    nloc = mesh.topology.index_map(fdim).size_local
    inner = np.flatnonzero(np.diff(f2c.offsets)[:nloc] == 2)[::7][:n].astype(np.int32)
    idx = np.concatenate([ft.indices, inner])
    val = np.concatenate([ft.values, np.full(len(inner), value, np.int32)])
    o = np.argsort(idx)
    return dolfinx.mesh.meshtags(mesh, fdim, idx[o], val[o])


def _pairs(ft):
    return set(zip(ft.indices.tolist(), ft.values.tolist(), strict=True))


def _marked_edges(mesh, centre, radius):
    tdim = mesh.topology.dim
    n = mesh.topology.index_map(tdim).size_local
    mid = dolfinx.mesh.compute_midpoints(mesh, tdim, np.arange(n, dtype=np.int32))
    cells = np.flatnonzero(np.linalg.norm(mid - centre, axis=1) < radius).astype(np.int32)
    mesh.topology.create_connectivity(tdim, 1)
    return dolfinx.mesh.compute_incident_entities(mesh.topology, cells, tdim, 1)


@pytest.mark.parametrize("case", ["dfg", "sphere"])
def test_tags_equal_transfer_meshtag(case):
    if case == "dfg":
        md = generate.dfg_channel(COMM, n_circle=16, h_far=0.1)
        tag, centre, radius = generate.CYLINDER, np.array([0.2, 0.2, 0.0]), 0.15
    else:
        md = generate.sphere_in_box(COMM, h_sphere=0.35, h_box=0.6)
        tag, centre, radius = generate.SPHERE, np.zeros(3), 0.8
    mesh, ft = md.mesh, _tag_interface(md.mesh, md.facet_tags, 77, 12)
    snapper = Snapper(mesh, ft, NagataGeometry(mesh, ft, tags=[tag]), tags=[tag])
    for level in range(3 if case == "dfg" else 2):
        edges = _marked_edges(mesh, centre, radius) if level == 1 else None
        mesh1, ft1, pc, pf, _ = snapper.refine(mesh, edges)
        ref = dolfinx.mesh.transfer_meshtag(ft, mesh1, pc, pf)
        assert _pairs(ft1) == _pairs(ref)
        assert np.count_nonzero(ft1.values == 77) > 0
        # the boundary found without facet entities is DOLFINx's exterior
        fdim = mesh1.topology.dim - 1
        ext = dolfinx.mesh.exterior_facet_indices(mesh1.topology)
        f_ext = snapper._level.boundary.facet_indices(mesh1)
        nloc = mesh1.topology.index_map(fdim).size_local
        assert set(f_ext[f_ext < nloc].tolist()) == set(ext.tolist())
        mesh, ft = mesh1, ft1


def _refined_once(md):
    """(mesh0, its boundary, mesh1, parent_cell, child facets) for one uniform refinement."""
    mesh0 = md.mesh
    mesh0.topology.create_entities(1)
    prev = boundary_facets(mesh0)
    mesh1, pc, _ = dolfinx.mesh.refine(mesh0, option=dolfinx.mesh.RefinementOption.parent_cell)
    return mesh0, prev, mesh1, pc, child_facets(mesh0, prev, mesh1, pc)


def test_weights_reproduce_children():
    mesh0, prev, mesh1, _, ch = _refined_once(generate.sphere_in_box(COMM, h_sphere=0.35, h_box=0.6))
    y = mesh1.geometry.x[ch.boundary.nodes]  # (nf, 3, 3)
    X = mesh0.geometry.x[prev.nodes[ch.parent]]
    assert np.abs(np.einsum("fvw,fwi->fvi", ch.weights, X) - y).max() < 1e-14
    assert set(np.unique(ch.weights).tolist()) <= {0.0, 0.5, 1.0}
    n = COMM.allreduce(len(ch.parent))
    assert n == 4 * COMM.allreduce(len(prev.cells))  # every boundary triangle in 4


def test_not_a_refinement_is_refused():
    mesh0, prev, mesh1, pc, ch = _refined_once(generate.dfg_channel(COMM, n_circle=16, h_far=0.1))
    # push one boundary midpoint off its parent edge: that child edge lies in
    # no parent facet, so the parent edge is no longer covered
    f, v = np.argwhere((ch.weights == 0.5).any(axis=2))[0]  # a vertex that is a midpoint
    node = ch.boundary.nodes[f, v]
    mesh1.geometry.x[node] += 1e-3 * np.array([1.0, 1.0, 0.0])
    with pytest.raises(LineageError, match="not covered"):
        child_facets(mesh0, prev, mesh1, pc)
