"""A gmsh mesh of a CAD file and its CadGeometry, with no search at attach.

:func:`mesh_cad` meshes a STEP, IGES or BREP file with
:func:`nagata_snap.meshing.mesh_cad_file` (gmsh) and reads the same file with
:meth:`CadGeometry.from_file` (OCP), in the same length unit.  gmsh knows
the entity every boundary facet was generated on and the ``(u, v)`` of its
vertices there; :func:`use_cad_mesh` matches gmsh's entities with the
geometry's faces (3D) or edge curves (2D) and records, per boundary facet,
its face and the vertices' parameters (:meth:`CadGeometry.set_mesh_hints`),
so that :meth:`CadGeometry.attach` (called by ``Snapper``) costs one seeded
projection per vertex and cannot pick a wrong face.

Matching is geometric: gmsh's sample points of an entity (inside its
trimmed face or curve) must lie on the matched face within 1e-7 of the
model size, inside its trimming loops; every gmsh entity must find one.  The
parameters are gmsh's where the two readers share the parametrisation
(analytic and B-spline faces; faces recognised as analytic through their
parameter map): checked on the samples, else the vertices are seeded from
the face's search samples.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from nagata_snap.cad.geometry import CadError, CadGeometry
from nagata_snap.cad.projection import entity_periods

if TYPE_CHECKING:
    from nagata_snap.meshing import CadMesh

__all__ = ["mesh_cad", "use_cad_mesh", "match_entities"]

#: gmsh samples must lie on their matched face within this fraction of the model size
MATCH_RTOL = 1e-7
#: a gmsh entity whose samples lie on no trimmed face matches the face whose surface holds them
#: and whose loops they leave by less than this fraction of the entity's box diagonal
LOOP_SLACK = 0.05


def match_entities(geometry: CadGeometry, entities: dict) -> dict:
    """Geometry entity of every gmsh face (3D) / curve (2D), and whether gmsh's parameters apply.

    Args:
        geometry: the CAD geometry.
        entities: ``{(dim, tag): EntityInfo}`` of :class:`nagata_snap.meshing.CadMesh`.

    Returns:
        ``{tag: (entity index, params_ok)}`` for the gmsh entities of dimension
        ``geometry.param_dim``.

    Raises:
        CadError: a gmsh entity lies on no face (curve) of the geometry.
    """
    d = geometry.param_dim
    tol = MATCH_RTOL * geometry.size
    infos = [e for (dim, _), e in sorted(entities.items()) if dim == d and len(e.points)]
    if not infos:
        return {}
    P = np.concatenate([e.points for e in infos])
    owner = np.repeat(np.arange(len(infos)), [len(e.points) for e in infos])
    res = geometry.searcher.search(P, accept=geometry._accept)
    ent, _, dist = res[:3]
    ok = dist <= tol if geometry._accept is None else (dist <= tol) & res[3]
    out = {}
    for k, info in enumerate(infos):  # loop over gmsh entities (a few samples each)
        rows = np.flatnonzero(owner == k)
        cand = np.unique(ent[rows][ok[rows]])
        best, best_d, best_p = None, np.inf, None
        for e in cand:  # the candidate on which all samples lie, nearest
            res_e = geometry.searcher.search_on(P[rows], np.full(len(rows), e), accept=geometry._accept)
            de = res_e[2].max() if geometry._accept is None or res_e[3].all() else np.inf
            if de < best_d:
                best, best_d, best_p = int(e), de, res_e[0]
        if best is None or not best_d <= tol:
            best, best_p = _nearly_inside(geometry, P[rows], info.bbox, tol)
        if best is None:
            raise CadError(
                f"gmsh {'surface' if d == 2 else 'curve'} {info.tag} ({info.kind}) lies on no "
                f"{'face' if d == 2 else 'edge'} of {geometry.model.path if geometry.model else 'the CAD'}"
                f" within {tol:.1e} (samples {np.round(info.points[:2], 6).tolist()}): the mesh and "
                "the CAD do not match (another file, unit or healing?)")
        assert best_p is not None  # set with best
        out[int(info.tag)] = (best, _same_params(geometry, best, info.params, best_p))
    return out


def _nearly_inside(geometry: CadGeometry, P: np.ndarray, bbox: np.ndarray, tol: float
                   ) -> tuple[int | None, np.ndarray | None]:
    """The face whose surface holds the samples ``P (m, 3)`` of a gmsh entity (within ``tol``) and
    whose trimming loops they leave least, if by less than :data:`LOOP_SLACK` of the entity's box.

    gmsh meshes a face in its parameter plane between the chords of its loops, so
    on a sliver face (a thread's end: 0.04 mm wide) its inner nodes can lie outside
    the exact loops; they are still on the face's surface.  ``bbox (2, 3)``: gmsh's
    box of the entity.  Returns ``(face, the samples' parameters on it)`` or ``(None, None)``.
    """
    slack = LOOP_SLACK * float(np.linalg.norm(bbox[1] - bbox[0]))
    best, best_x, best_p = None, np.inf, None
    for e, ent in enumerate(geometry.entities):  # loop over faces (only for an unmatched entity)
        lo, hi = ent.bbox
        if not (np.all(lo - tol <= P) and np.all(hi + tol >= P)):
            continue
        par, _, dist = geometry.searcher.search_on(P, np.full(len(P), e))[:3]
        if not dist.max() <= tol:
            continue
        out = 0.0 if geometry.trims is None else float(np.max(geometry.trims.excess(np.full(len(P), e), par)))
        if out < best_x:
            best, best_x, best_p = e, out, par
    return (best, best_p) if best_x <= slack else (None, None)


def _same_params(geometry: CadGeometry, e: int, gmsh_params: np.ndarray, ours: np.ndarray) -> bool:
    """gmsh's parameters of the samples are the geometry's (through the face's map), mod periods."""
    g = np.asarray(gmsh_params, dtype=float).reshape(len(ours), -1)
    if g.shape[1] != geometry.param_dim:
        return False
    g = _mapped(geometry, e, g)
    per = entity_periods(geometry.entities[e])
    diff = ours.reshape(len(g), -1) - g
    for a in np.flatnonzero(np.isfinite(per)):
        diff[:, a] -= per[a] * np.round(diff[:, a] / per[a])
    span = np.maximum(np.ptp(geometry.entities[e].bounds, axis=1), 1e-300)
    return bool(np.all(np.abs(diff) <= 1e-7 * span))


def _mapped(geometry: CadGeometry, e: int, uv: np.ndarray) -> np.ndarray:
    """gmsh's (the file's) parameters on entity ``e`` in the geometry's parameters."""
    m = geometry.model
    if m is None or geometry.param_dim != 2 or m.faces[e].uv_map is None:
        return uv
    return np.c_[uv, np.ones(len(uv))] @ m.faces[e].uv_map


def use_cad_mesh(geometry: CadGeometry, cad_mesh: CadMesh) -> None:
    """Record a :class:`~nagata_snap.meshing.CadMesh`'s facets as the geometry's mesh hints.

    After this, :meth:`CadGeometry.attach` of the mesh's boundary facets (by
    their input-global node ids, as ``Snapper`` passes them) takes each facet's
    face and its vertices' parameters from gmsh.

    Raises:
        CadError: gmsh's entities and the geometry's faces do not match.
    """
    match = match_entities(geometry, cad_mesh.entities)
    tags = np.asarray(cad_mesh.facet_entity, dtype=np.int64)
    if tags.size and not set(np.unique(tags).tolist()) <= set(match):
        missing = sorted(set(np.unique(tags).tolist()) - set(match))
        raise CadError(f"boundary facets lie on gmsh entities {missing[:5]} without samples to match")
    lut = dict(match.items())
    faces = np.array([lut[int(t)][0] for t in tags], dtype=np.int64)
    params = np.asarray(cad_mesh.node_params, dtype=float).copy()
    for t in np.unique(tags):
        sel = tags == t
        e, ok = lut[int(t)]
        if ok:
            params[sel] = _mapped(geometry, e, params[sel].reshape(-1, params.shape[2])).reshape(
                params[sel].shape)
        else:
            params[sel] = np.nan
    gids = np.asarray(cad_mesh.mesh.geometry.input_global_indices, dtype=np.int64)[cad_mesh.facets.nodes]
    geometry.set_mesh_hints(gids, faces, params)


def _exterior_tags(cad_mesh: CadMesh) -> np.ndarray:
    """Facet tag values on this process's exterior facets (not the faces two solids share)."""
    from nagata_snap.mesh.boundary import tag_values

    return np.unique(tag_values(cad_mesh.facet_tags, cad_mesh.facets.facet_indices(cad_mesh.mesh)))


def mesh_cad(path: str | Path, comm: Any = None, *, unit: str = "MM", geometry_options: dict | None = None,
             **mesh_options: Any) -> tuple[CadMesh, CadGeometry]:
    """Mesh a CAD file with gmsh and read it as a :class:`CadGeometry` that knows the mesh.

    Args:
        path: STEP, IGES or BREP file.
        comm: MPI communicator (default ``MPI.COMM_WORLD``); collective.
        unit: length unit of mesh and geometry (see :meth:`CadGeometry.from_file`).
        geometry_options: passed to :meth:`CadGeometry.from_file`.
        **mesh_options: passed to :func:`nagata_snap.meshing.mesh_cad_file`
            (``size``, ``curvature``, ``per_face_tags``, ...).

    Returns:
        ``(cad_mesh, geometry)``: ``cad_mesh.mesh`` and ``cad_mesh.facet_tags``
        go to ``Snapper(mesh, facet_tags, geometry)``; ``geometry.tags`` are
        the facet tags of the exterior boundary (what ``Snapper`` snaps by
        default; a face two solids share is interior).

    Raises:
        CadError: the file cannot be read (by OCP), or its entities in gmsh do not
            match the faces OCP read.
        ValueError, RuntimeError: from the mesher (see ``mesh_cad_file``).
        All on every process.
    """
    import mpi4py.MPI as MPI

    from nagata_snap.mesh.parallel import collective
    from nagata_snap.meshing import mesh_cad_file

    comm = MPI.COMM_WORLD if comm is None else comm
    cad_mesh = mesh_cad_file(path, comm, unit=unit, **mesh_options)
    geometry = CadGeometry.from_file(path, unit=cad_mesh.unit or unit, comm=comm,
                                     **(geometry_options or {}))
    collective(comm, use_cad_mesh, geometry, cad_mesh)
    # Snapper snaps these by default: the exterior faces' tags (an assembly's shared face is interior)
    tags = np.unique(np.concatenate(comm.allgather(_exterior_tags(cad_mesh))))
    geometry.tags = [int(t) for t in tags if t >= 0]
    return cad_mesh, geometry
