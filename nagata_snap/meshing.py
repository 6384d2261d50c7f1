"""Mesh a CAD file with gmsh and keep what gmsh knows about each boundary facet.

:func:`mesh_cad_file` opens a STEP, IGES or BREP file in gmsh's OpenCASCADE
kernel, meshes it (size from ``size`` or a fraction of the model's diagonal,
curvature sizing), converts the mesh with :func:`dolfinx.io.gmsh.model_to_mesh`
(serial or distributed) and returns a :class:`CadMesh`: the DOLFINx mesh and
tags, and for every exterior facet that this process owns (the facets of
:func:`nagata_snap.mesh.boundary.boundary_facets`, in that order)

* the gmsh entity it was generated on (surface tag in 3D, curve tag in 2D),
* for each of its vertices: the parametric coordinates on that entity and the
  entity the vertex is classified on (a vertex on a CAD edge or corner is
  known as such),

plus a few sample points per gmsh entity, so that the CAD side can match
gmsh's entities with its own faces geometrically, and the length unit.

Matching is exact, not geometric: DOLFINx keeps gmsh's node numbering as the
geometry's input global indices (``mesh.geometry.input_global_indices`` =
gmsh node tag - 1), so a DOLFINx facet and the gmsh element it came from have
the same node set.  gmsh runs on one process (``rank``); it builds a table over
its boundary elements (sorted vertex indices, entity, parametric
coordinates) and over the nodes classified on boundary entities, broadcasts
it (O(boundary) data), and every process looks its own facets up with one
sorted search.

Parametric coordinates come from gmsh: nodes inside a face carry the (u, v)
gmsh meshed them at; nodes on a curve or a point are reparametrised on the
face (``gmsh.model.reparametrizeOnSurface``).  On a seam a node has two (u, v);
each facet takes the one on the side of its other nodes.  At a pole or apex
(where one parametric derivative vanishes) the free parameter is set to the
mean of the facet's other nodes, so the facet's (u, v) triangle is the one
gmsh meshed.  In 2D the nodes carry the parameter t on the curve (a point
closing a closed curve: the end of the range next to the facet's other node).

Units: OpenCASCADE converts STEP and IGES coordinates to its session unit
(the static ``xstep.cascade.unit``, millimetres by default; gmsh's option
``Geometry.OCCTargetUnit`` sets it, and it stays set for later imports in the
process).  :func:`import_cad` therefore sets it to millimetres explicitly for
every import and scales to the requested ``unit`` with ``Geometry.OCCScaling``
(gmsh 4.15 cannot set the target unit for an IGES file before any STEP file
has been read in the process, but then the static still has its default,
millimetres).  ``CadMesh.unit`` states the unit; a reader of the same file
(OCP's ``STEPControl_Reader`` / ``IGESControl_Reader``, whose default is also
millimetres) must use the same.  BREP files carry no unit: their coordinates
are taken as stored (``CadMesh.unit`` None, no scaling).

IGES files carry faces, not solids (unless written in B-rep mode): the faces
are sewn into a solid (``occ.healShapes`` with sewing only: OpenCASCADE's
degenerate-edge fix removes the region around a pole or apex of a face) with a
tolerance of ``1e-5`` of the model's diagonal.  Several solids (an assembly)
are fragmented so that a face they share is one face and the mesh is
conformal.

A coarse mesh can be too coarse for its first refinement's snapping: where a
boundary facet's edge midpoint lies farther from the CAD than the cell on
that facet is high (a thread's flank meshed at 12 elements per 2 pi of the
helix), snapping the new vertex inverts the cells and the guard can only
leave it short.  :func:`move_ratio` measures that (the midpoints' distances
from their gmsh entity, from ``gmsh.model.getClosestPoint``, over the heights
of the cells on the facets) and :func:`mesh_cad_file` doubles the curvature
sizing while it exceeds ``max_move_ratio`` (up to :data:`MAX_CURVATURE`),
saying so in ``CadMesh.meshed_with``.

The gmsh session is left as found: initialised (and finalised) here only if
it was not, otherwise a new model is added and removed and every option set
here is restored.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import dolfinx.mesh
import mpi4py.MPI as MPI
import numpy as np
import numpy.typing as npt

from nagata_snap.errors import MeshingError, missing_extra
from nagata_snap.mesh.boundary import BoundaryFacets, boundary_facets
from nagata_snap.mesh.parallel import collective

try:
    import gmsh
    from dolfinx.io import gmsh as _dxgmsh
except ImportError as _e:  # the [cad] extra
    raise missing_extra("gmsh", "to mesh CAD files") from _e

__all__ = ["CadMesh", "EntityInfo", "MeshAttempt", "MeshingError", "RETRIES", "mesh_cad_file", "import_cad",
           "gmsh_session", "CAD_SUFFIXES"]

#: file suffixes :func:`mesh_cad_file` reads, and gmsh's name of each format
CAD_SUFFIXES = {".step": "step", ".stp": "step", ".igs": "iges", ".iges": "iges",
                ".brep": "brep", ".brp": "brep"}

#: sewing tolerance for faces-only files (IGES), relative to the model's diagonal
SEW_TOLERANCE = 1e-5

#: millimetres per length unit (OpenCASCADE's names for ``xstep.cascade.unit``)
UNITS_MM = {"MM": 1.0, "CM": 10.0, "M": 1000.0, "KM": 1.0e6, "UM": 1.0e-3, "INCH": 25.4,
            "FT": 304.8, "MI": 1609344.0, "MIL": 0.0254, "UIN": 2.54e-5}


# ----------------------------------------------------------------------
# result types
# ----------------------------------------------------------------------
@dataclass
class EntityInfo:
    """A gmsh model entity, with samples for matching it with another CAD reader's.

    Attributes:
        dim, tag: the gmsh entity (the tags of a model imported from a file are
            its OpenCASCADE shapes in the file's order, renumbered by healing
            and fragmenting).
        kind: ``gmsh.model.getType`` (``"Plane"``, ``"Cylinder"``, ``"Cone"``,
            ``"Sphere"``, ``"Torus"``, ``"BSpline surface"``, ``"Line"``,
            ``"Circle"``, ``"BSpline"``, ...; ``"Unknown"`` for e.g. surfaces of
            extrusion).
        bbox: ``(2, 3)`` lower and upper corner of gmsh's bounding box [unit].
        param_bounds: ``(2, pdim)`` lower and upper parametric bounds (``pdim = dim``;
            empty for points).
        points: ``(m, 3)`` points on the entity, inside its trimmed face / curve
            (parametric centres of m of its mesh elements, m <= 5; for points the
            point itself).
        params: ``(m, pdim)`` their parametric coordinates.
        boundary: tags of the entities of dimension ``dim - 1`` bounding it.
    """

    dim: int
    tag: int
    kind: str
    bbox: np.ndarray
    param_bounds: np.ndarray
    points: np.ndarray
    params: np.ndarray
    boundary: tuple[int, ...]


@dataclass
class CadMesh:
    """A gmsh mesh of a CAD file as DOLFINx objects, with gmsh's classification of its boundary.

    Per-facet arrays run over ``facets`` (the exterior facets whose cell this
    process owns, :func:`nagata_snap.mesh.boundary.boundary_facets`); ``nfv`` = 2
    (2D) or 3 (3D) vertices per facet, in the order of ``facets.nodes``;
    ``pdim = tdim - 1`` parameters per vertex.

    Attributes:
        mesh: the DOLFINx mesh (gdim = tdim: 2 for a planar part, else 3).
        facet_tags: one tag per CAD face (3D) / curve (2D), equal to its gmsh
            entity tag (``per_face_tags=True``), else tag 1 on the whole exterior boundary.
        cell_tags: the gmsh volume (3D) / surface (2D) tag of each cell.
        facets: the owned exterior facets.
        facet_entity: ``(nf,)`` gmsh entity (surface in 3D, curve in 2D) each facet lies on.
        node_params: ``(nf, nfv, pdim)`` parametric coordinates of each facet
            vertex on ``facet_entity`` (consistent within the facet across seams,
            see the module docstring).
        node_entity_dim, node_entity_tag: ``(nf, nfv)`` the gmsh entity each
            facet vertex is classified on (dimension 0: a CAD corner, 1: on a CAD
            edge (3D), ``tdim - 1``: inside ``facet_entity``).
        entities: ``{(dim, tag): EntityInfo}`` for every gmsh entity of
            dimension < tdim (the boundary's faces, edges and corners).
        unit: the length unit of the coordinates (STEP, IGES: the ``unit``
            asked for, default ``"MM"``), None for BREP (no unit in the file).
        size: the mesh size used (``Mesh.MeshSizeMax``) [unit].
        model_size: diagonal of the model's bounding box [unit].
        path: the file.
        times: seconds per stage on the gmsh process (``import``, ``mesh``,
            ``table``) and on every process (``distribute``, ``match``).
        meshed_with: the retry (:data:`RETRIES`) that meshed the model, and the
            finer curvature sizing used for snapping (:func:`move_ratio`), in
            words; ``""``: the options asked for.
        move_ratio: :func:`move_ratio` of the mesh returned (nan: not measured,
            ``order`` 2 or ``max_move_ratio=None``).
    """

    mesh: dolfinx.mesh.Mesh
    facet_tags: dolfinx.mesh.MeshTags
    cell_tags: dolfinx.mesh.MeshTags
    facets: BoundaryFacets
    facet_entity: npt.NDArray[np.int32]
    node_params: npt.NDArray[np.float64]
    node_entity_dim: npt.NDArray[np.int32]
    node_entity_tag: npt.NDArray[np.int32]
    entities: dict[tuple[int, int], EntityInfo]
    unit: str | None
    size: float
    model_size: float
    path: Path
    times: dict[str, float] = field(default_factory=dict)
    meshed_with: str = ""
    move_ratio: float = math.nan


# ----------------------------------------------------------------------
# gmsh session and import
# ----------------------------------------------------------------------
@contextlib.contextmanager
def gmsh_session(model_name: str, options: dict[str, float | str] | None = None
                 ) -> Iterator[Callable[[str, float | str], None]]:
    """A new current gmsh model ``model_name`` with ``options`` set; gmsh left as found afterwards.

    gmsh is initialised (quiet: ``General.Terminal = 0``) if it is not, and
    then finalised on exit; in a caller's session the model is removed, every
    option set restored and the previous current model made current again.

    Yields:
        ``set_option(key, value)``: sets a gmsh option (number or string) to be
        restored on exit.
    """
    was_init = gmsh.isInitialized()
    if not was_init:
        gmsh.initialize(argv=[], readConfigFiles=False, interruptible=False)
        gmsh.option.setNumber("General.Terminal", 0)
    previous = gmsh.model.getCurrent() if was_init else None
    saved: dict[str, float | str] = {}

    def set_option(key: str, value: float | str) -> None:
        if isinstance(value, str):
            saved.setdefault(key, gmsh.option.getString(key))
            gmsh.option.setString(key, value)
        else:
            saved.setdefault(key, gmsh.option.getNumber(key))
            gmsh.option.setNumber(key, value)

    try:
        for key, value in (options or {}).items():
            set_option(key, value)
        gmsh.model.add(model_name)
        yield set_option
    finally:
        if not was_init:
            gmsh.finalize()
        else:
            with contextlib.suppress(Exception):
                if gmsh.model.getCurrent() == model_name:
                    gmsh.model.remove()
            for key, value in saved.items():
                setter = gmsh.option.setString if isinstance(value, str) else gmsh.option.setNumber
                setter(key, value)
            if previous:
                with contextlib.suppress(Exception):
                    gmsh.model.setCurrent(previous)


@contextlib.contextmanager
def console_off(off: bool = True) -> Iterator[None]:
    """File descriptors 1 and 2 to ``/dev/null`` while inside (with ``off``).

    gmsh's own log obeys ``General.Terminal``, but the OpenCASCADE inside gmsh
    prints to the process's standard output directly (the IGES reader's
    "Total number of loaded entities", coloured), so only the descriptors
    can keep it off the user's terminal.  Python's and C's buffers are
    flushed on the way in and out, so nothing written before or inside
    comes out elsewhere.
    """
    if not off:
        yield
        return
    libc = ctypes.CDLL(None)
    sys.stdout.flush()
    sys.stderr.flush()
    libc.fflush(None)
    saved = [os.dup(1), os.dup(2)]
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 1)
        os.dup2(null, 2)
        yield
    finally:
        libc.fflush(None)
        for fd, old in zip((1, 2), saved, strict=True):
            os.dup2(old, fd)
            os.close(old)
        os.close(null)


def _diagonal() -> float:
    b = gmsh.model.getBoundingBox(-1, -1)
    return math.dist(b[:3], b[3:])


def _remove_free_faces() -> None:
    """Remove the faces that bound no solid from a model with solids.

    gmsh's import of a faces-only IGES file sews the faces into a solid but
    can keep the unsewn originals beside it; meshed, their nodes belong to no
    cell, which DOLFINx cannot distribute (it aborts the MPI job).  Such
    faces are not part of the domain's boundary."""
    free = [(2, t) for _, t in gmsh.model.getEntities(2) if len(gmsh.model.getAdjacencies(2, t)[0]) == 0]
    if free:
        gmsh.model.occ.remove(free, recursive=True)
        gmsh.model.occ.synchronize()


def import_cad(path: str | Path, unit: str = "MM") -> tuple[int, list[int]]:
    """Import a STEP, IGES or BREP file into the current gmsh model (OpenCASCADE) and synchronise.

    Solids are kept (several are fragmented into one conformal model; faces
    beside them that bound no solid are removed); a faces-only file is sewn
    into a solid; a file of planar faces in z = 0 and
    no solid is a 2D part.  STEP and IGES coordinates are converted to
    ``unit`` (a key of ``UNITS_MM``; see the module docstring), BREP
    coordinates are taken as stored.

    Returns:
        ``(tdim, tags)``: 3 and the volume tags, or 2 and the surface tags.

    Raises:
        FileNotFoundError: no such file.
        ValueError: an unknown suffix or unit, a file gmsh cannot read, no
            shapes in it, or shapes that make neither a solid nor a planar part.
    """
    path = Path(path)
    if path.suffix.lower() not in CAD_SUFFIXES:
        raise ValueError(f"{path}: unknown CAD file suffix {path.suffix!r}; "
                         f"use one of {', '.join(CAD_SUFFIXES)}")
    if unit.upper() not in UNITS_MM:
        raise ValueError(f"unknown length unit {unit!r}; use one of {', '.join(UNITS_MM)}")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such CAD file")
    _read_shapes(path, unit.upper())
    occ = gmsh.model.occ
    if not gmsh.model.getEntities():
        raise ValueError(f"{path}: the file contains no shapes (empty model)")
    if len(gmsh.model.getEntities(3)) > 1:
        occ.removeAllDuplicates()  # fragment: a face shared by two solids becomes one face
        occ.synchronize()
    if gmsh.model.getEntities(3):
        _remove_free_faces()
        return 3, [t for _, t in gmsh.model.getEntities(3)]
    faces = [t for _, t in gmsh.model.getEntities(2)]
    if faces and _planar_in_xy(faces):
        if len(faces) > 1:
            occ.removeAllDuplicates()
            occ.synchronize()
        return 2, [t for _, t in gmsh.model.getEntities(2)]
    if faces:
        _sew_into_solid(faces)
    vols = [t for _, t in gmsh.model.getEntities(3)]
    if not vols:
        raise ValueError(f"{path}: no solid in the file and its {len(faces)} faces do not close "
                         f"into one (sewing tolerance {SEW_TOLERANCE:g} x the model's diagonal); "
                         "a 2D part must be planar faces in the plane z = 0.  To try next: export the "
                         "solid (not only its faces) from your CAD system, or mesh the region these "
                         "faces bound yourself (e.g. gmsh with the faces as its boundary) and snap "
                         "that mesh onto the file (nagata-snap part.msh --cad FILE)")
    _remove_free_faces()  # the sewn solid's faces can be copies of the file's
    return 3, vols


def _read_shapes(path: Path, unit: str) -> None:
    """``occ.importShapes`` in millimetres scaled to ``unit`` (STEP, IGES); options restored."""
    fmt = CAD_SUFFIXES[path.suffix.lower()]
    saved = gmsh.option.getString("Geometry.OCCTargetUnit"), gmsh.option.getNumber("Geometry.OCCScaling")
    try:
        if fmt != "brep":
            gmsh.option.setNumber("Geometry.OCCScaling", 1.0 / UNITS_MM[unit])
        for target in ("MM", ""):  # "": the static was never set in this process, so it is MM
            gmsh.option.setString("Geometry.OCCTargetUnit", target if fmt != "brep" else "")
            try:
                with console_off():  # OpenCASCADE's readers print past General.Terminal
                    gmsh.model.occ.importShapes(str(path), highestDimOnly=True, format=fmt)
                break
            except Exception as exc:
                if target == "MM" and "target unit" in str(exc):
                    continue
                raise ValueError(f"{path}: gmsh/OpenCASCADE cannot read this file ({exc})") from None
    finally:
        gmsh.option.setString("Geometry.OCCTargetUnit", saved[0])
        gmsh.option.setNumber("Geometry.OCCScaling", saved[1])
    gmsh.model.occ.synchronize()


def _planar_in_xy(faces: list[int]) -> bool:
    """Whether every face is a plane z = 0 (normal and a point checked at the parametric centre)."""
    tol = 1e-9 * _diagonal()
    for f in faces:
        if gmsh.model.getType(2, f) != "Plane":
            return False
        lo, hi = gmsh.model.getParametrizationBounds(2, f)
        uv = 0.5 * (np.asarray(lo) + np.asarray(hi))
        if abs(gmsh.model.getNormal(f, uv)[2]) < 1.0 - 1e-12 or abs(gmsh.model.getValue(2, f, uv)[2]) > tol:
            return False
    return True


def _sew_into_solid(faces: list[int]) -> None:
    """Sew faces into a solid (no degenerate-edge or small-feature fixes, which damage poles)."""
    occ = gmsh.model.occ
    occ.healShapes([], tolerance=SEW_TOLERANCE * _diagonal(), fixDegenerated=False,
                   fixSmallEdges=False, fixSmallFaces=False, sewFaces=True, makeSolids=True)
    occ.synchronize()
    if not gmsh.model.getEntities(3) and _closed_shell():  # sewn but not made a solid: close it
        with contextlib.suppress(Exception):
            occ.addVolume([occ.addSurfaceLoop([t for _, t in gmsh.model.getEntities(2)], sewing=True)])
        occ.synchronize()


def _closed_shell() -> bool:
    """Whether every curve bounds two faces, or one face twice (a seam), or is degenerate."""
    for _, c in gmsh.model.getEntities(1):  # a few hundred curves at most
        up = gmsh.model.getAdjacencies(1, c)[0]
        if len(up) == 1:
            uses = [t for _, t in gmsh.model.getBoundary([(2, int(up[0]))], combined=False, oriented=False)]
            if uses.count(c) < 2 and gmsh.model.getType(1, c) != "Unknown":
                return False
        elif len(up) != 2:
            return False
    return True


# ----------------------------------------------------------------------
# meshing (on the gmsh process)
# ----------------------------------------------------------------------
#: gmsh options that make a mesh reproducible, node for node (one thread, fixed algorithms:
#: Frontal-Delaunay in 2D, Delaunay in 3D)
DETERMINISTIC_OPTIONS = {
    "General.NumThreads": 1,
    "Mesh.MaxNumThreads1D": 1,
    "Mesh.MaxNumThreads2D": 1,
    "Mesh.MaxNumThreads3D": 1,
    "Geometry.OCCParallel": 0,
    "Mesh.Algorithm": 6,
    "Mesh.Algorithm3D": 1,
}


def _mesh_options(size: float, min_size: float, curvature: float, order: int, verbose: bool) -> dict:
    return {
        **DETERMINISTIC_OPTIONS,
        "General.Terminal": 1 if verbose else 0,
        "General.Verbosity": 4 if verbose else 1,
        "Mesh.MeshSizeMax": size,
        "Mesh.MeshSizeMin": min_size,
        "Mesh.MeshSizeFromCurvature": curvature,
        "Mesh.MeshSizeFromPoints": 0,
        "Mesh.MeshSizeExtendFromBoundary": 1,
        "Mesh.ElementOrder": order,
        "Mesh.SecondOrderLinear": 0,
        "Mesh.Optimize": 1,
        "Mesh.SaveAll": 0,
    }


@dataclass(frozen=True)
class MeshAttempt:
    """A change to the meshing options asked for, tried when gmsh fails with them.

    Attributes:
        size_scale: factor on the element size (and on the smallest size).
        toggle_curvature: curvature sizing off if it was on, on
            (:data:`RETRY_CURVATURE` elements per 2 pi) if it was off.
        options: gmsh options set on top of the others (another algorithm).
        tdim: the model dimension it applies to (None: both).
    """

    size_scale: float = 1.0
    toggle_curvature: bool = False
    options: dict[str, float] = field(default_factory=dict)
    tdim: int | None = None

    def curvature(self, asked: float) -> float:
        """Elements per 2 pi of curvature for this attempt, given the ``asked`` value."""
        return (0.0 if asked > 0 else RETRY_CURVATURE) if self.toggle_curvature else asked

    def describe(self, asked: float) -> str:
        """The change in words (``asked``: the curvature sizing asked for)."""
        parts = [] if self.size_scale == 1.0 else [f"{self.size_scale:g} x the element size"]
        if self.toggle_curvature:
            parts.append("curvature sizing off" if asked > 0 else
                         f"curvature sizing on ({RETRY_CURVATURE:g} elements per 2 pi)")
        parts += [f"{_ALGORITHMS.get((k, v), k)} ({k} = {v:g})" for k, v in self.options.items()]
        return ", ".join(parts) or "the options asked for"


#: elements per 2 pi of curvature where a retry switches curvature sizing on
RETRY_CURVATURE = 12.0
#: the default ``max_move_ratio`` of :func:`mesh_cad_file` (:func:`move_ratio`).  Above 1
#: the guard must untangle or slide; on the corpus (meshes/corpus, 12 per 2 pi) the solids
#: stay below 0.6 but for the Pro/E frame (2.3: snaps with 0 vertices short, some slid) and
#: the M6 screw's thread (27: 284 vertices left short; 1.1 at 24 per 2 pi, 0 short)
MAX_MOVE_RATIO = 3.0
#: the finest curvature sizing :func:`mesh_cad_file` goes to for snapping
MAX_CURVATURE = 48.0
#: the names of the gmsh algorithms the retries use
_ALGORITHMS: dict[tuple[str, float], str] = {("Mesh.Algorithm", 1): "gmsh's MeshAdapt surface algorithm",
               ("Mesh.Algorithm3D", 10): "gmsh's HXT volume algorithm"}
#: what :func:`mesh_cad_file` tries, in this order, when gmsh fails to mesh the model with
#: the options asked for (e.g. "Invalid boundary mesh (overlapping facets)" at a coarse
#: size): each attempt changes one thing from the options asked for
RETRIES = (
    MeshAttempt(size_scale=0.5),
    MeshAttempt(toggle_curvature=True),
    MeshAttempt(options={"Mesh.Algorithm": 1}),
    MeshAttempt(options={"Mesh.Algorithm3D": 10}, tdim=3),
)


def _physical_groups(tdim: int, tops: list[int], per_face: bool) -> None:
    """One group per top entity (tag = entity tag); one per boundary face, or one (tag 1) for all."""
    for t in tops:
        gmsh.model.addPhysicalGroup(tdim, [t], t)
    if per_face:
        for _, t in gmsh.model.getEntities(tdim - 1):  # one group per CAD face: a few hundred at most
            gmsh.model.addPhysicalGroup(tdim - 1, [t], t)
    else:
        outer = gmsh.model.getBoundary([(tdim, t) for t in tops], combined=True, oriented=False)
        gmsh.model.addPhysicalGroup(tdim - 1, sorted({t for _, t in outer}), 1, name="boundary")


def _mesh_with_retries(path: Path, unit: str, tdim: int, tops: list[int], per_face_tags: bool, h: float,
                       h_min: float, curvature: float, order: int, verbose: bool,
                       retries: Sequence[MeshAttempt], on_retry: Callable[[str], None] | None,
                       set_option, times: dict[str, float], own_gmsh: bool) -> tuple[dict, float, str]:
    """Mesh the imported model with the options asked for, then with each of ``retries`` until
    one gives a mesh (and its boundary table).

    A failed attempt can leave gmsh unusable (a retry, even of the file
    imported afresh into a new model, then generates no 3D elements), so every
    retry restarts gmsh where this call initialised it (``own_gmsh``; else it
    only imports the file into a new model) and imports the file again.

    Returns:
        ``(table, size, what)``: the boundary table, the element size used,
        and the retry that worked in words (``""``: the options asked for).

    Raises:
        MeshingError: every attempt failed; names gmsh's failure of each.
    """
    attempts = [MeshAttempt()] + [r for r in retries if r.tdim in (None, tdim)]
    failures: list[str] = []
    sizes: list[float] = []
    for k, a in enumerate(attempts):
        if k:
            name = gmsh.model.getCurrent()
            if own_gmsh:
                gmsh.finalize()
                gmsh.initialize(argv=[], readConfigFiles=False, interruptible=False)
                gmsh.option.setNumber("General.Terminal", 1 if verbose else 0)
            else:
                gmsh.model.remove()
            gmsh.model.add(name)
            import_cad(path, unit)
        _physical_groups(tdim, tops, per_face_tags)
        size = h * a.size_scale
        options = {**_mesh_options(size, h_min * a.size_scale, a.curvature(curvature), order, verbose),
                   **a.options}
        for key, value in options.items():
            set_option(key, value)
        try:
            t0 = time.perf_counter()
            with console_off(not verbose):
                _generate(tdim, order, path, verbose)
            times["mesh"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            table = _boundary_table(tdim)
            times["table"] = time.perf_counter() - t0
            return table, size, "" if k == 0 else a.describe(curvature)
        except MeshingError as e:
            sizes.append(size)
            failures.append(f"{a.describe(curvature)} (size {size:.4g}): {e}")
            if on_retry is not None and k + 1 < len(attempts):
                on_retry(f"gmsh failed to mesh {path.name} with {failures[-1]}; retrying with "
                         f"{attempts[k + 1].describe(curvature)}")
    raise MeshingError(f"{path}: gmsh could not mesh the model with " + "; nor with ".join(failures),
                       tuple(sizes))


def _generate(tdim: int, order: int, path: Path, verbose: bool) -> None:
    """Mesh dimension by dimension (progress printed with ``verbose``)."""
    for d in range(1, tdim + 1):
        t0 = time.perf_counter()
        try:
            gmsh.model.mesh.generate(d)
        except Exception as exc:
            raise MeshingError(f"gmsh failed to mesh dimension {d}: {exc}") from None
        if verbose:
            n = sum(len(t) for t in gmsh.model.mesh.getElements(d)[1])
            print(f"nagata_snap.meshing: {path.name}: {d}D mesh, {n} elements, "
                  f"{time.perf_counter() - t0:.2f} s", flush=True)
    n_top = sum(len(t) for t in gmsh.model.mesh.getElements(tdim)[1])
    if n_top == 0:
        raise MeshingError(f"gmsh generated no {tdim}D elements")
    _check_facets_on_cells(tdim, path)
    if order > 1:
        gmsh.model.mesh.setOrder(order)
    gmsh.model.mesh.renumberNodes()  # contiguous tags 1..N, as model_to_mesh expects


def _check_facets_on_cells(tdim: int, path: Path) -> None:
    """Every node of a tagged boundary face must be a node of a cell; else DOLFINx cannot
    distribute the facet tags (it aborts the MPI job), so the face is named here instead."""
    cell_nodes = np.concatenate([np.asarray(n) for n in gmsh.model.mesh.getElements(tdim)[2]])
    loose = []
    for _, group in gmsh.model.getPhysicalGroups(tdim - 1):
        for t in gmsh.model.getEntitiesForPhysicalGroup(tdim - 1, group):
            nodes = np.concatenate([np.asarray(n) for n in gmsh.model.mesh.getElements(tdim - 1, t)[2]] or
                                   [np.zeros(0, dtype=np.uint64)])
            if not np.isin(nodes, cell_nodes).all():
                loose.append(int(t))
    if loose:
        raise RuntimeError(f"{path}: gmsh {'surfaces' if tdim == 3 else 'curves'} "
                           f"{', '.join(map(str, sorted(set(loose))))} are meshed but bound no "
                           f"{'tetrahedron' if tdim == 3 else 'triangle'} (faces beside the solid, or "
                           "overlapping faces); remove them from the file or mesh its solids only")


# ----------------------------------------------------------------------
# the boundary table (on the gmsh process)
# ----------------------------------------------------------------------
def _classified_nodes(tdim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(input index, dim, tag) of the nodes on entities of dimension < tdim, sorted by index."""
    parts: tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]] = ([], [], [])
    for d, t in gmsh.model.getEntities():
        if d >= tdim:
            continue
        n = gmsh.model.mesh.getNodes(d, t, includeBoundary=False, returnParametricCoord=False)[0]
        parts[0].append(n.astype(np.int64) - 1)
        parts[1].append(np.full(len(n), d, dtype=np.int32))
        parts[2].append(np.full(len(n), t, dtype=np.int32))
    idx, dims, tags = (np.concatenate(a) for a in parts)
    order = np.argsort(idx)
    return idx[order], dims[order], tags[order]


def _candidates(tdim: int, ent: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Parametric coordinates on boundary entity ``ent`` of the nodes in its closure (its
    boundary and the entities embedded in it).

    Returns ``(nodes, params, inner, free)``: sorted input indices ``(n,)``,
    ``(n, pdim)`` parameters (nodes on the face's curves and points
    reparametrised on it; on a seam either side), ``(n,)`` whether the node is
    inside the entity, and ``(n, pdim)`` flags of the parameters that are free
    at a node (pole or apex: the surface's derivative with respect to it vanishes).
    """
    fdim = tdim - 1
    tags, x, uv = gmsh.model.mesh.getNodes(fdim, ent, includeBoundary=False, returnParametricCoord=True)
    param_parts = [np.reshape(uv, (-1, fdim))]
    node_parts, x_parts = [tags.astype(np.int64) - 1], [np.reshape(x, (-1, 3))]
    below = {(d, t) for d, t in gmsh.model.getBoundary([(fdim, ent)], combined=False, oriented=False)}
    # and the points / curves embedded in it (e.g. a sphere's pole where OpenCASCADE's
    # degenerate edge was): gmsh's elements of the face use their nodes too
    below |= {(int(d), int(t)) for d, t in gmsh.model.mesh.getEmbedded(fdim, ent)}
    if fdim == 2:
        curves = [e for e in below if e[0] == 1]
        below |= set(gmsh.model.getBoundary(curves, combined=False, oriented=False)) if curves else set()
    for d, t in sorted(below):  # the face's curves and points: a few each
        tags, x, tp = gmsh.model.mesh.getNodes(d, t, includeBoundary=False, returnParametricCoord=True)
        if len(tags):
            node_parts.append(tags.astype(np.int64) - 1)
            x_parts.append(np.reshape(x, (-1, 3)))
            param_parts.append(_reparametrize(fdim, ent, d, t, tp))
    n_inner = len(param_parts[0])
    nodes, X, params = (np.concatenate(a) for a in (node_parts, x_parts, param_parts))
    inner = np.arange(len(nodes)) < n_inner
    free = np.zeros(params.shape, dtype=bool)
    if fdim == 2 and len(params) > n_inner:
        D = np.reshape(gmsh.model.getDerivative(2, ent, params[n_inner:].ravel()), (-1, 2, 3))
        free[n_inner:] = np.linalg.norm(D, axis=2) <= 1e-12 * _diagonal()
        polish = np.flatnonzero(~inner & ~free.any(axis=1))
        params[polish] = _foot_point(ent, X[polish], params[polish])
    order = np.argsort(nodes)
    return nodes[order], params[order], inner[order], free[order]


def _foot_point(face: int, x: np.ndarray, uv: np.ndarray, iterations: int = 2) -> np.ndarray:
    """(u, v) of the points of surface ``face`` closest to ``x (n, 3)``, by Gauss-Newton from ``uv``.

    A node on a CAD edge is on the edge's 3D curve; its p-curve on the face
    agrees with it only to the edge's tolerance (e.g. 1e-7 on intersection
    curves): the foot point puts (u, v) where the face is nearest the node.
    A step is kept only where it brings the surface point nearer.
    """
    if len(x) == 0:
        return uv
    for _ in range(iterations):
        S = np.reshape(gmsh.model.getValue(2, face, uv.ravel()), (-1, 3))
        J = np.reshape(gmsh.model.getDerivative(2, face, uv.ravel()), (-1, 2, 3))
        r = x - S
        A = np.einsum("nij,nkj->nik", J, J)
        g = np.einsum("nij,nj->ni", J, r)
        det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] ** 2
        ok = det > 1e-300
        det = np.where(ok, det, 1.0)
        step = np.stack([A[:, 1, 1] * g[:, 0] - A[:, 0, 1] * g[:, 1],
                         A[:, 0, 0] * g[:, 1] - A[:, 0, 1] * g[:, 0]], axis=1) / det[:, None]
        new = uv + np.where(ok[:, None], step, 0.0)
        Sn = np.reshape(gmsh.model.getValue(2, face, new.ravel()), (-1, 3))
        better = np.linalg.norm(x - Sn, axis=1) < np.linalg.norm(r, axis=1)
        uv = np.where(better[:, None], new, uv)
    return uv


def _reparametrize(fdim: int, ent: int, d: int, t: int, tp: np.ndarray) -> np.ndarray:
    """``(n, pdim)`` parameters on ``ent`` of the nodes of entity ``(d, t)`` (curve parameters ``tp``)."""
    if fdim == 2:
        return np.reshape(gmsh.model.reparametrizeOnSurface(d, t, tp if d == 1 else [], ent), (-1, 2))
    # 2D: a point at an end of curve ent (the nearer end; a closed curve is unwrapped later)
    lo, hi = gmsh.model.getParametrizationBounds(1, ent)
    ends = np.array([lo[0], hi[0]])
    x = np.reshape(gmsh.model.getValue(1, ent, ends), (2, 3))
    dist = np.linalg.norm(x - np.asarray(gmsh.model.getValue(0, t, [])), axis=1)
    return ends[[np.argmin(dist)]][:, None]


def _closed_directions(fdim: int, ent: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(lo, hi, closed)``: parametric bounds and, per parameter, whether the entity closes on itself
    there (its values at the two bounds agree: a seam, or a closed curve)."""
    lo, hi = (np.asarray(b, dtype=float) for b in gmsh.model.getParametrizationBounds(fdim, ent))
    tol = 1e-9 * _diagonal()
    if fdim == 1:
        a, b = np.reshape(gmsh.model.getValue(1, ent, [lo[0], hi[0]]), (2, 3))
        return lo, hi, np.array([np.linalg.norm(a - b) <= tol])
    s = lo[::-1] + (hi - lo)[::-1] * np.array([[0.2], [0.5], [0.8]])  # samples of the other parameter
    closed = np.zeros(2, dtype=bool)
    for k in range(2):
        at = np.empty((2, 3, 2))
        at[:, :, k] = np.array([[lo[k]], [hi[k]]])
        at[:, :, 1 - k] = s[:, k]
        S = np.reshape(gmsh.model.getValue(2, ent, at.ravel()), (2, 3, 3))
        closed[k] = np.linalg.norm(S[0] - S[1], axis=1).max() <= tol
    return lo, hi, closed


def _element_params(tdim: int, ent: int, enodes: np.ndarray) -> np.ndarray:
    """``(E, nfv, pdim)`` parameters on ``ent`` of the vertices ``enodes (E, nfv)`` of its elements.

    gmsh meshed each element inside the parametric bounds; a vertex on a
    seam takes the bound (lower or upper) nearer the element's reference
    vertex (inside the entity if it has one, else one off the seam); a free
    parameter (pole) takes the mean of the element's other vertices.
    """
    fdim = tdim - 1
    nodes, p, inner, free = _candidates(tdim, ent)
    pos = np.searchsorted(nodes, enodes)
    if len(nodes) == 0 or np.any(nodes[np.minimum(pos, len(nodes) - 1)] != enodes):
        raise MeshingError(f"gmsh's elements of entity ({fdim}, {ent}) use nodes off its boundary and "
                           "embedded entities")
    c, fr = p[pos], free[pos]  # (E, nfv, pdim)
    lo, hi, closed = _closed_directions(fdim, ent)
    if closed.any():
        period = hi - lo
        on_seam = closed & ((np.abs(c - lo) <= 1e-9 * period) | (np.abs(c - hi) <= 1e-9 * period))
        score = np.where(inner[pos], 0, np.where((on_seam | fr).any(axis=2), 2, 1))
        ref = c[np.arange(len(c)), np.argmin(score, axis=1)][:, None, :]
        shifted = c[..., None] + period[:, None] * np.array([-1.0, 0.0, 1.0])  # (E, nfv, pdim, 3)
        inside = (shifted >= (lo - 1e-9 * period)[:, None]) & (shifted <= (hi + 1e-9 * period)[:, None])
        dist = np.where(inside, np.abs(shifted - ref[..., None]), np.inf)
        best = np.take_along_axis(shifted, np.argmin(dist, axis=3)[..., None], axis=3)[..., 0]
        c = np.where(closed, best, c)
    if fr.any():
        fixed = np.where(fr, 0.0, c)
        count = (~fr).sum(axis=1, keepdims=True) - (~fr)  # other vertices with that parameter fixed
        mean = (fixed.sum(axis=1, keepdims=True) - fixed) / np.maximum(count, 1)
        c = np.where(fr & (count > 0), mean, c)
    return c


def _entity_info(d: int, t: int, samples: tuple[np.ndarray, np.ndarray] | None) -> EntityInfo:
    """gmsh's description of entity (d, t); ``samples`` (points, params) if already known."""
    b = np.reshape(gmsh.model.getBoundingBox(d, t), (2, 3))
    if d > 0:
        lo, hi = gmsh.model.getParametrizationBounds(d, t)
        bounds = np.array([lo, hi], dtype=float)
    else:
        bounds = np.zeros((2, 0))
    if samples is None:
        if d == 0:
            params = np.zeros((1, 0))
            points = np.reshape(gmsh.model.getValue(0, t, []), (1, 3))
        else:
            _, _, tp = gmsh.model.mesh.getNodes(d, t, includeBoundary=False, returnParametricCoord=True)
            tp = np.reshape(tp, (-1, d))
            params = tp[_spread(len(tp))] if len(tp) else 0.5 * (bounds[:1] + bounds[1:])
            points = np.reshape(gmsh.model.getValue(d, t, params.ravel()), (-1, 3))
        samples = (points, params)
    bnd = tuple(sorted({tb for _, tb in gmsh.model.getBoundary([(d, t)], combined=False, oriented=False)})) \
        if d > 0 else ()
    return EntityInfo(d, t, gmsh.model.getType(d, t), b, bounds, samples[0], samples[1], bnd)


def _spread(n: int, m: int = 5) -> np.ndarray:
    """Up to ``m`` indices spread over ``range(n)``."""
    return np.unique(np.linspace(0, n - 1, min(n, m)).round().astype(np.int64))


def _boundary_table(tdim: int) -> dict:
    """The boundary elements with entity and parameters, the classified nodes, the entity infos."""
    fdim = tdim - 1
    keys, ents, params, infos = [], [], [], {}
    for _, e in gmsh.model.getEntities(fdim):  # loop over CAD faces (2D: curves)
        etypes, _, enodes = gmsh.model.mesh.getElements(fdim, e)
        if len(etypes) == 0:
            infos[(fdim, e)] = _entity_info(fdim, e, None)
            continue
        nn = gmsh.model.mesh.getElementProperties(etypes[0])[3]
        vert = (np.reshape(enodes[0], (-1, nn))[:, :tdim]).astype(np.int64) - 1
        p = _element_params(tdim, e, vert)
        sample = _spread(len(vert))
        centre = p[sample].mean(axis=1)
        infos[(fdim, e)] = _entity_info(
            fdim, e, (np.reshape(gmsh.model.getValue(fdim, e, centre.ravel()), (-1, 3)), centre))
        order = np.argsort(vert, axis=1)
        keys.append(np.take_along_axis(vert, order, axis=1))
        params.append(np.take_along_axis(p, order[:, :, None], axis=1))
        ents.append(np.full(len(vert), e, dtype=np.int32))
    for d in range(fdim):
        for _, t in gmsh.model.getEntities(d):
            infos[(d, t)] = _entity_info(d, t, None)
    node_index, node_dim, node_tag = _classified_nodes(tdim)
    return {"keys": np.concatenate(keys), "entity": np.concatenate(ents), "params": np.concatenate(params),
                "node_index": node_index, "node_dim": node_dim, "node_tag": node_tag, "entities": infos}


def move_ratio(tdim: int, table: dict) -> tuple[float, int]:
    """How far the first refinement will move the boundary, over the boundary cells' heights.

    For every boundary element of the current gmsh mesh (``table``: its
    :func:`_boundary_table`, linear elements): the largest distance of one of its
    edge midpoints (where the first refinement puts new vertices) from the gmsh
    entity it lies on, over the height of the cell on that element (3 x volume /
    area; 2D: 2 x area / length).  Above 1 a new vertex snapped onto the CAD
    passes the cell's opposite vertex, which no smoothing of the interior undoes.

    Returns:
        ``(ratio, entity)``: the largest ratio and the entity tag where it occurs
        (``(0.0, -1)`` without boundary elements).
    """
    fdim = tdim - 1
    keys, ent = table["keys"], table["entity"]
    if len(keys) == 0:
        return 0.0, -1
    x = np.reshape(gmsh.model.mesh.getNodes()[1], (-1, 3))  # node k + 1 in row k (renumbered)
    etypes, _, enodes = gmsh.model.mesh.getElements(tdim)
    nn = gmsh.model.mesh.getElementProperties(etypes[0])[3]
    cells = (np.reshape(enodes[0], (-1, nn))[:, :tdim + 1]).astype(np.int64) - 1
    # every cell facet as sorted vertex keys, with the cell's vertex opposite it
    local = np.array([[j for j in range(tdim + 1) if j != i] for i in range(tdim + 1)])
    cfacets = np.sort(cells[:, local].reshape(-1, tdim), axis=1)
    opposite = cells.reshape(-1)  # facet i of a cell is opposite its vertex i
    ck = _row_view(cfacets)
    sort = np.argsort(ck, kind="stable")
    pos = np.minimum(np.searchsorted(ck[sort], _row_view(keys)), len(sort) - 1)
    apex = x[opposite[sort[pos]]]
    p = x[keys]  # (nb, tdim, 3)
    if tdim == 3:
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        edges = [(0, 1), (1, 2), (0, 2)]
    else:
        t = p[:, 1] - p[:, 0]
        n = np.c_[-t[:, 1], t[:, 0], np.zeros(len(t))]
        edges = [(0, 1)]
    height = np.abs(np.einsum("ij,ij->i", apex - p[:, 0], n)) / np.maximum(
        np.linalg.norm(n, axis=1), np.finfo(float).tiny)
    mids = np.stack([(p[:, a] + p[:, b]) / 2 for a, b in edges], axis=1)  # (nb, ne, 3)
    dist = np.zeros(mids.shape[:2])
    for e in np.unique(ent):  # one closest-point call per CAD face (2D: curve)
        rows = np.flatnonzero(ent == e)
        cp = gmsh.model.getClosestPoint(fdim, int(e), mids[rows].ravel())[0]
        dist[rows] = np.linalg.norm(np.reshape(cp, (len(rows), -1, 3)) - mids[rows], axis=2)
    ratio = dist.max(axis=1) / np.maximum(height, np.finfo(float).tiny)
    k = int(np.argmax(ratio))
    return float(ratio[k]), int(ent[k])


# ----------------------------------------------------------------------
# the DOLFINx side
# ----------------------------------------------------------------------
def _row_view(a: np.ndarray) -> np.ndarray:
    """Rows of an int64 array as one structured scalar each (lexicographic order)."""
    a = np.ascontiguousarray(a, dtype=np.int64)
    return a.view([(f"f{i}", np.int64) for i in range(a.shape[1])]).ravel()


def _match(mesh: dolfinx.mesh.Mesh, table: dict, path: Path) -> tuple:
    """Per owned exterior facet: entity, vertex parameters, vertex classification."""
    facets = boundary_facets(mesh)
    igi = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)[facets.nodes]
    order = np.argsort(igi, axis=1)
    key = np.take_along_axis(igi, order, axis=1)
    tkeys = _row_view(table["keys"])
    sort = np.argsort(tkeys, kind="stable")
    q = _row_view(key)
    pos = np.minimum(np.searchsorted(tkeys[sort], q), len(sort) - 1)
    row = sort[pos]
    missing = np.flatnonzero(tkeys[row] != q) if len(q) else np.zeros(0, dtype=np.int64)
    if len(missing):
        x = mesh.geometry.x[facets.nodes[missing[0]]].round(6).tolist()
        raise RuntimeError(f"{path}: {len(missing)} boundary facets of the DOLFINx mesh match no "
                           f"gmsh boundary element (first at {x}): a face without physical group?")
    rank = np.argsort(order, axis=1)  # position of each facet vertex in the sorted key
    params = np.take_along_axis(table["params"][row], rank[:, :, None], axis=1)
    npos = np.searchsorted(table["node_index"], igi)
    npos = np.minimum(npos, max(len(table["node_index"]) - 1, 0))
    if np.any(table["node_index"][npos] != igi):
        raise RuntimeError(f"{path}: boundary vertices not classified on a boundary entity by gmsh")
    return (facets, table["entity"][row].astype(np.int32), params,
            table["node_dim"][npos].astype(np.int32), table["node_tag"][npos].astype(np.int32))


def mesh_cad_file(
    path: str | Path,
    comm: MPI.Comm = MPI.COMM_WORLD,
    *,
    size: float | None = None,
    size_factor: float = 0.1,
    min_size: float | None = None,
    curvature: float = 12,
    per_face_tags: bool = True,
    order: int = 1,
    unit: str = "MM",
    rank: int = 0,
    partitioner: Callable | None = None,
    verbose: bool = False,
    retries: Sequence[MeshAttempt] = RETRIES,
    on_retry: Callable[[str], None] | None = None,
    max_move_ratio: float | None = MAX_MOVE_RATIO,
) -> CadMesh:
    """Mesh a STEP, IGES or BREP file with gmsh (OpenCASCADE) into a DOLFINx mesh.

    Args:
        path: the CAD file (``.step/.stp``, ``.igs/.iges``, ``.brep/.brp``), read
            on process ``rank``.
        comm: the communicator the mesh is distributed over (collective).
        size: largest element size [unit] (``Mesh.MeshSizeMax``); default
            ``size_factor`` x the model's bounding-box diagonal.
        size_factor: see ``size``.
        min_size: smallest element size [unit] (``Mesh.MeshSizeMin``), default
            ``size / 50``: curvature sizing refines at most that far (it must be
            bounded: at a cone's apex the curvature is infinite and gmsh would
            split edges forever).
        curvature: elements per 2 pi of curvature (``Mesh.MeshSizeFromCurvature``;
            0 switches curvature sizing off).
        per_face_tags: one facet tag per CAD face (3D) / curve (2D), equal to
            gmsh's entity tag; else tag 1 on the whole exterior boundary.
        order: 1 (affine, what :class:`nagata_snap.Snapper` refines) or 2 (mid-nodes
            on the CAD, from gmsh); the per-vertex data cover the facets' vertices.
        unit: the length unit STEP and IGES coordinates are converted to
            (``"MM"``, OpenCASCADE's default; ``"M"``, ``"INCH"``, ... : ``UNITS_MM``);
            BREP coordinates are taken as stored.
        rank: the process that runs gmsh.
        partitioner: passed to :func:`dolfinx.io.gmsh.model_to_mesh` (None:
            DOLFINx's default, no ghost cells).
        verbose: print gmsh's log and the time per meshing stage (on ``rank``).
        retries: what to try, in order, if gmsh fails to mesh the model with
            the options asked for (:data:`RETRIES`; ``()``: nothing); the first
            that works is used (:attr:`CadMesh.meshed_with` says which).
        on_retry: called on ``rank`` with a line saying what failed and what
            is tried next, before each retry (None: silent).
        max_move_ratio: while the first refinement would move boundary vertices
            more than this many times their cells' heights (:func:`move_ratio`),
            the model is meshed again with twice the curvature sizing (up to
            :data:`MAX_CURVATURE`; ``on_retry`` says so); None: never.

    Returns:
        :class:`CadMesh` (per-facet arrays over this process's owned exterior facets).

    Raises:
        FileNotFoundError: no such file.
        ValueError: unknown suffix, unreadable or empty file, no solid (3D) and
            no planar face in z = 0 (2D), bad ``size`` / ``order``.
        MeshingError: gmsh failed to mesh the model, with the options asked
            for and with every retry (a ``RuntimeError``; the message names
            gmsh's failure of each attempt).
        All on every process of ``comm``.
    """
    path = Path(path)
    if order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, got {order}")
    for name, value in (("size", size), ("min_size", min_size)):
        if value is not None and not (value > 0 and math.isfinite(value)):
            raise ValueError(f"{name} must be a positive length, got {value}")
    root = comm.rank == rank
    own_gmsh = root and not gmsh.isInitialized()  # a retry may restart it
    session = gmsh_session(f"cad:{path.name}") if root else contextlib.nullcontext()
    times: dict[str, float] = {}
    with session as set_option:
        table = collective(comm, _mesh_on_root if root else lambda *a: None, path, size, size_factor,
                           min_size, curvature, per_face_tags, order, unit, verbose, times, set_option,
                           retries, on_retry, own_gmsh, max_move_ratio)
        table = comm.bcast(table, root=rank)
        t0 = time.perf_counter()
        data = _dxgmsh.model_to_mesh(gmsh.model if root else None, comm, rank, gdim=table["tdim"],
                                     partitioner=partitioner)
    times.update(comm.bcast(times, root=rank))
    times["distribute"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    facets, entity, params, ndim, ntag = collective(comm, _match, data.mesh, table, path)
    times["match"] = time.perf_counter() - t0
    # _physical_groups always adds physical groups of the cells and of the facets
    assert data.facet_tags is not None and data.cell_tags is not None
    return CadMesh(data.mesh, data.facet_tags, data.cell_tags, facets, entity, params, ndim, ntag,
                   table["entities"], table["unit"], table["size"], table["model_size"], path, times,
                   table["meshed_with"], table["move_ratio"])


def _mesh_on_root(path, size, size_factor, min_size, curvature, per_face_tags, order, unit, verbose, times,
                  set_option, retries, on_retry, own_gmsh, max_move_ratio) -> dict:
    """Import, mesh and tabulate on the gmsh process (options through ``set_option``)."""
    set_option("General.Terminal", 1 if verbose else 0)
    t0 = time.perf_counter()
    tdim, tops = import_cad(path, unit)
    times["import"] = time.perf_counter() - t0
    model_size = _diagonal()
    h = float(size) if size is not None else size_factor * model_size
    h_min = h / 50.0 if min_size is None else float(min_size)
    table, h, meshed_with = _mesh_with_retries(path, unit, tdim, tops, per_face_tags, h, h_min, curvature,
                                               order, verbose, retries, on_retry, set_option, times, own_gmsh)
    ratio = math.nan
    if max_move_ratio is not None and order == 1:
        used = gmsh.option.getNumber("Mesh.MeshSizeFromCurvature")  # a retry may have changed it
        table, ratio, finer = _finer_for_snapping(path, tdim, table, used, max_move_ratio, order,
                                                  verbose, on_retry, set_option, times)
        meshed_with = ", ".join(w for w in (meshed_with, finer) if w)
    table.update(tdim=tdim, size=h, model_size=model_size, meshed_with=meshed_with, move_ratio=ratio,
                 unit=None if CAD_SUFFIXES[path.suffix.lower()] == "brep" else unit.upper())
    return table


def _finer_for_snapping(path: Path, tdim: int, table: dict, curvature: float, max_ratio: float, order: int,
                        verbose: bool, on_retry: Callable[[str], None] | None, set_option,
                        times: dict[str, float]) -> tuple[dict, float, str]:
    """Re-mesh with twice the curvature sizing while :func:`move_ratio` exceeds ``max_ratio``
    (up to :data:`MAX_CURVATURE`); ``(table, ratio, what was done in words)``.

    Only with curvature sizing on (``curvature > 0``, as asked or by a retry): the
    moves are sagittas of curved faces, which it shrinks.  If a finer mesh fails,
    the last one that worked is made again.
    """
    t0 = time.perf_counter()
    ratio, ent = move_ratio(tdim, table)
    times["move_ratio"] = time.perf_counter() - t0
    start, what = ratio, ""
    while ratio > max_ratio and 0 < curvature < MAX_CURVATURE:
        finer = min(2 * curvature, MAX_CURVATURE)
        note = (f"the first level would move boundary vertices {ratio:.2g} x the height of their "
                f"cells (gmsh {'surface' if tdim == 3 else 'curve'} {ent}, curvature sizing "
                f"{curvature:g} per 2 pi)")
        if on_retry is not None:
            on_retry(f"{path.name}: {note}; meshing again with {finer:g} elements per 2 pi")
        gmsh.model.mesh.clear()
        set_option("Mesh.MeshSizeFromCurvature", finer)
        try:
            with console_off(not verbose):
                _generate(tdim, order, path, verbose)
        except MeshingError:  # keep the last mesh that worked
            gmsh.model.mesh.clear()
            set_option("Mesh.MeshSizeFromCurvature", curvature)
            with console_off(not verbose):
                _generate(tdim, order, path, verbose)
            table = _boundary_table(tdim)
            what = f"curvature sizing {curvature:g} per 2 pi ({finer:g} failed)"
            break
        table, curvature = _boundary_table(tdim), finer
        ratio, ent = move_ratio(tdim, table)
        what = (f"curvature sizing {curvature:g} per 2 pi for snapping (boundary moves over cell "
                f"heights {start:.2g} -> {ratio:.2g})")
    times["finer"] = time.perf_counter() - t0 - times["move_ratio"]
    return table, ratio, what
