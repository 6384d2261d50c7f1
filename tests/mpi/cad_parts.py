"""CAD parts end to end: mesh with gmsh, snap with CadGeometry, check against OpenCASCADE.

Usage: [mpiexec -n N] python cad_parts.py OUT.json PART:FORMAT:SIZE_FACTOR:CURVATURE[,...]

For every part of ``meshes/parts.py`` and file format (``step``, ``iges``,
``iges_brep``): rank 0 writes the file, :func:`nagata_snap.cad.mesh_cad`
meshes it (gmsh, coarse) and reads it (OCP), ``Snapper`` refines 3D parts
twice uniformly and twice on marked cells (2D parts: three uniform levels).
After every level each process checks its own snapped facets against
OpenCASCADE (``BRepExtrema_DistShapeShape`` on the shape read from the same
file, faces and edges numbered as the geometry's):

* every vertex's distance to its facet's face (2D: edge curve; OCC's exact
  answer where it is above 1e-9 of the model size, else a bound below it);
* every vertex whose facets lie on two or more faces: its distance to the
  nearest CAD edge of each of those faces (3D), also less the edge's
  tolerance (the edge curves of an IGES file are approximations within it;
  the vertex is put on the faces' intersection);
* every vertex on three or more faces (2D: on two edge curves): its distance to the
  nearest CAD vertex;
* inverted cells against the straight refinement of the previous level.

(gmsh: ``size_factor`` x the model's diagonal, ``curvature`` elements per
2 pi: coarse, but fine enough that the current smoother needs no partial
moves, which would leave vertices off the CAD.)

Rank 0 writes, per part and level, the maxima over all processes (relative
to the model size) to OUT.json.
"""

import json
import os
import sys
import time

import mpi4py.MPI as MPI
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [os.path.join(HERE, ".."), os.path.join(HERE, "..", "..", "meshes")]
import parts  # noqa: E402
from occ_reference import OccShape  # noqa: E402

import dolfinx.mesh  # noqa: E402

from nagata_snap import Snapper  # noqa: E402
from nagata_snap.cad import mesh_cad  # noqa: E402
from nagata_snap.mesh import bisect  # noqa: E402
from nagata_snap.smoothing.quality import inverted_cells  # noqa: E402

comm = MPI.COMM_WORLD


def _abort(*exc_info):
    """An exception on one process ends all of them (no hang in a collective of the others)."""
    sys.__excepthook__(*exc_info)
    comm.Abort(1)


sys.excepthook = _abort


def marked_edges(mesh, centre, radius):
    """Edges of the cells whose midpoint is within ``radius`` of ``centre``."""
    tdim = mesh.topology.dim
    cells = np.arange(mesh.topology.index_map(tdim).size_local, dtype=np.int32)
    mid = dolfinx.mesh.compute_midpoints(mesh, tdim, cells)
    near = cells[np.linalg.norm(mid[:, :3] - centre, axis=1) < radius]
    mesh.topology.create_connectivity(tdim, 1)
    return dolfinx.mesh.compute_incident_entities(mesh.topology, near, tdim, 1)


def file_params(geo, faces, uv):
    """The file's (OCC's) parameters of ``uv (n, 2)`` on the geometry's faces (NaN where they
    differ: faces converted to NURBS)."""
    out = np.array(uv, dtype=float)
    for f in np.unique(faces):
        face, sel = geo.model.faces[f], faces == f
        if face.converted:
            out[sel] = np.nan
        elif face.uv_map is not None:  # [u, v, 1] M = ours
            out[sel] = (uv[sel] - face.uv_map[2]) @ np.linalg.inv(face.uv_map[:2])
    return out


def feature_distances(geo, occ, nodes, root, x, tdim):
    """Largest distance of edge vertices to the nearest CAD edge of each of their faces, and
    of corner vertices (3D: on three or more faces; 2D: on two edge curves) to the nearest
    CAD vertex (this process's facets).

    Edges are compared per face, not as the faces' common edge: the solids of
    an assembly touch without sharing edges in the file (gmsh fragments them).
    """
    model = geo.model
    faces_of = {}
    for n, f in zip(nodes.ravel(), np.repeat(root, nodes.shape[1]), strict=True):
        faces_of.setdefault(int(n), set()).add(int(f))
    pairs, corner = [], []
    for n, fs in faces_of.items():
        if len(fs) < 2:
            continue
        if tdim == 3:
            pairs += [(n, f) for f in fs]
        if len(fs) >= tdim:
            corner.append(x[n])
    de = de_tol = 0.0
    if pairs:  # per (vertex, face): the nearest of the face's edges
        flat = [(k, e) for k, (n, f) in enumerate(pairs) for e in model.faces[f].edges]
        d = occ.edge_distance([e for _, e in flat], [x[pairs[k][0]] for k, _ in flat], 1e-9 * occ.size)
        tol = np.array([model.edges[e].tolerance for _, e in flat])
        best = np.full(len(pairs), np.inf)
        beyond = np.full(len(pairs), np.inf)
        np.minimum.at(best, np.array([k for k, _ in flat]), d)
        np.minimum.at(beyond, np.array([k for k, _ in flat]), np.maximum(d - tol, 0.0))
        de, de_tol = float(best.max()), float(beyond.max())
    dc = 0.0
    if corner:
        C = np.asarray(corner)
        dc = float(np.linalg.norm(C[:, None] - model.vertices[None], axis=2).min(axis=1).max())
    return de, de_tol, dc, len({n for n, _ in pairs}), len(corner)


def run(name, fmt, size_factor, curvature):
    path = os.path.join(outdir, f"{name}{parts.EXTENSIONS[fmt]}")
    if comm.rank == 0 and not os.path.exists(path):
        parts.write_part(name, outdir, (fmt,))
    comm.barrier()
    t0 = time.perf_counter()
    cm, geo = mesh_cad(path, comm, size_factor=size_factor, curvature=curvature)
    t_mesh = time.perf_counter() - t0
    mesh = cm.mesh
    tdim = mesh.topology.dim
    t0 = time.perf_counter()
    snapper = Snapper(mesh, cm.facet_tags, geo)
    t_attach = time.perf_counter() - t0
    occ = OccShape(path, cm.unit or "MM")
    size = occ.size
    lo, hi = np.empty(3), np.empty(3)
    comm.Allreduce(mesh.geometry.x.min(axis=0), lo, op=MPI.MIN)
    comm.Allreduce(mesh.geometry.x.max(axis=0), hi, op=MPI.MAX)
    modes = ["uniform"] * 3 if tdim == 2 else ["uniform", "uniform", "marked", "marked"]
    levels = []
    for mode in modes:
        edges = None if mode == "uniform" else marked_edges(
            mesh, lo + (hi - lo) * np.array([0.35, 0.45, 0.6]), 0.06 * np.linalg.norm(hi - lo))
        prev = mesh
        t0 = time.perf_counter()
        mesh, *_, report = snapper.refine(mesh, edges)
        t_level = time.perf_counter() - t0
        lv = snapper._level
        sel = np.flatnonzero(lv.snapped)
        nodes, root = lv.boundary.nodes[sel], lv.records.root
        x = mesh.geometry.x
        _, first = np.unique(np.c_[nodes.ravel(), np.repeat(root, nodes.shape[1])], axis=0, return_index=True)
        P, F = x[nodes].reshape(-1, 3)[first], np.repeat(root, nodes.shape[1])[first]
        t1 = time.perf_counter()
        accept = 1e-9 * size  # OCC's answer is exact above this bound, an upper bound below it
        if tdim == 3:
            uv = file_params(geo, F, lv.records.params[..., :2].reshape(-1, 2)[first])
            d_own = occ.face_distance(F, P, accept, uv)
        else:
            d_own = occ.edge_distance(geo._curve_edges[F], P, accept)
        de, de_tol, dc, ne, nc = feature_distances(geo, occ, nodes, root, x, tdim)
        # inverted cells against the straight refinement of the previous level
        prev.topology.create_entities(1)
        straight, *_ = bisect.refine(prev, edges)  # the snapper's refinement, not snapped
        cells = mesh.geometry.dofmaps[0][: mesh.topology.index_map(tdim).size_local]
        same = np.array_equal(straight.geometry.dofmaps[0][: len(cells)], cells)
        inv = inverted_cells(x, straight.geometry.x, cells, tdim).size if same else -1
        t_check = time.perf_counter() - t1
        g = report.geometry
        levels.append({
            "mode": mode,
            "cells": comm.allreduce(mesh.topology.index_map(tdim).size_local),
            "own": comm.allreduce(float(d_own.max(initial=0.0)), op=MPI.MAX) / size,
            "edge": comm.allreduce(de, op=MPI.MAX) / size,
            "edge_beyond_tolerance": comm.allreduce(de_tol, op=MPI.MAX) / size,
            "corner": comm.allreduce(dc, op=MPI.MAX) / size,
            "edge_vertices": comm.allreduce(ne), "corner_vertices": comm.allreduce(nc),
            "inverted": comm.allreduce(inv) if comm.allreduce(int(inv < 0)) == 0 else -1,
            "inverted_after_smoothing": int(report.inverted_after_smoothing),
            "partially_moved": int(getattr(report, "partially_moved", 0) or 0),
            "moved": int(report.boundary_vertices_moved),
            "unresolved": int(g.n_unresolved), "fallback": comm.allreduce(int(g.n_fallback)),
            "max_edge_gap": comm.allreduce(float(g.max_edge_gap), op=MPI.MAX) / size,
            "seconds": comm.allreduce(t_level, op=MPI.MAX),
            "check_seconds": comm.allreduce(t_check, op=MPI.MAX),
        })
    return {"part": name, "format": fmt, "faces": geo.num_entities, "summary": geo.model.summary(),
            "coarse_cells": comm.allreduce(cm.mesh.topology.index_map(tdim).size_local),
            "mesh_seconds": t_mesh, "attach_seconds": t_attach, "levels": levels}


out = sys.argv[1]
outdir = os.path.join(os.path.dirname(os.path.abspath(out)), "parts")
os.makedirs(outdir, exist_ok=True)
cases = [c.split(":") for c in sys.argv[2].split(",")]
results = [run(name, fmt, float(sf), float(cu)) for name, fmt, sf, cu in cases]
if comm.rank == 0:
    with open(out, "w") as f:
        json.dump(results, f, indent=1)
