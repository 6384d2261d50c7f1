"""``nagata-snap``: refine a mesh (or a CAD part) and snap its curved boundary.

A thin command line around :class:`~nagata_snap.NagataGeometry`
(:class:`~nagata_snap.FittedGeometry` with ``--surface fitted``),
:class:`~nagata_snap.cad.CadGeometry` and :class:`~nagata_snap.Snapper`::

    nagata-snap part.step --size 5 --levels 2 --output fine.xdmf --plot levels.png
    nagata-snap mesh.msh --tags 4 --levels 2 --output fine.xdmf
    nagata-snap mesh.xdmf --tags 2 --cad part.igs --output fine.bp --report
    mpiexec -n 4 nagata-snap mesh.vtu --tag-key medit:ref --tags 3 --output fine.xdmf

(also ``python -m nagata_snap.cli``).  A CAD file (``.step/.stp``,
``.igs/.iges``, ``.brep``) is meshed by gmsh (``--size``, curvature sizing)
and every exterior face is snapped onto it (:func:`nagata_snap.cad.mesh_cad`:
the facets' faces come from gmsh, no search).  Mesh inputs: gmsh ``.msh``
(read as ``dolfinx.io.gmsh.read_from_msh`` does; facet tags from the
physical groups of dimension d-1), ``.xdmf`` (``dolfinx.io.XDMFFile``: a mesh
and a facet MeshTags grid, e.g. as written by this command) and anything
meshio reads (linear triangles or tetrahedra; facet tags from the cell data
``gmsh:physical`` or the key given by ``--tag-key``), snapped onto Nagata
patches or onto a CAD file given with ``--cad``.

Each level prints a line (cells, vertices, snapped vertices, time), and a
long level a heartbeat every 10 s; the summary gives the vertices left short
of the geometry and (CAD) the largest distance of a boundary vertex from its
face.  ``--plot FILE.png`` draws per level the histograms of the changed
cells' quality (minimum angle, mean ratio) and of the boundary vertices'
distance from the CAD.

Where gmsh fails to mesh a CAD input with the options given (e.g. "Invalid
boundary mesh (overlapping facets)"), the command retries with half the
size, curvature sizing toggled and other gmsh algorithms
(:data:`nagata_snap.meshing.RETRIES`), printing each retry; if all fail,
the error names gmsh's failures and the flags to try next.  gmsh's and
OpenCASCADE's own console output is kept off the terminal.

Exit status: 0 on success, 2 for unusable input (missing or unreadable
files, unknown tags, bad options, a part gmsh cannot mesh with them), 1 if
snapping itself fails (e.g. cells would invert); the reason is printed as
``nagata-snap: error: ...`` on standard error.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import mpi4py.MPI as MPI
import numpy as np

if TYPE_CHECKING:
    import dolfinx.mesh

    from nagata_snap.cad import CadGeometry
    from nagata_snap.geometry import SnapGeometry

#: what the inputs give: the coarse mesh, its facet tags, a CAD geometry (None: Nagata
#: patches) and the tags to snap (None: the geometry's or all)
_Input = tuple["dolfinx.mesh.Mesh", "dolfinx.mesh.MeshTags", "CadGeometry | None", "Sequence[int] | None"]

__all__ = ["main"]

PROG = "nagata-snap"

#: XDMF topology types -> topological dimension
_XDMF_DIM = {
    "polyvertex": 0, "polyline": 1, "edge_3": 1, "triangle": 2, "triangle_6": 2,
    "quadrilateral": 2, "quadrilateral_8": 2, "quadrilateral_9": 2, "tetrahedron": 3,
    "tetrahedron_10": 3, "hexahedron": 3, "hexahedron_20": 3, "hexahedron_27": 3,
    "wedge": 3, "pyramid": 3,
}


class UserError(Exception):
    """Unusable input: reported without traceback, exit status 2."""


class SnapFailure(Exception):
    """Snapping failed on valid input: reported without traceback, exit status 1."""


# --------------------------------------------------------------------------
# readers
# --------------------------------------------------------------------------
def tag_list(tags) -> str:
    """Tag values as text, runs of consecutive values as ranges.

    >>> tag_list([1, 2, 3, 4, 7, 9, 10])
    '1-4, 7, 9, 10'
    """
    t = np.unique(np.asarray(tags, dtype=np.int64))
    if t.size == 0:
        return "none"
    cut = np.flatnonzero(np.diff(t) != 1) + 1
    runs = np.split(t, cut)  # a run of 3 or more is a range, shorter ones are listed
    return ", ".join(f"{r[0]}-{r[-1]}" if len(r) > 2 else ", ".join(map(str, r)) for r in runs)


def _bcast_checked(comm, value: Any, error: str | None) -> Any:
    """Broadcast ``(value, error)`` from rank 0; raise UserError everywhere on error."""
    value, error = comm.bcast((value, error), root=0)
    if error:
        raise UserError(error)
    return value


def read_msh(path: str, comm):
    """gmsh ``.msh`` -> (mesh, facet_tags); gdim is 2 for planar 2D meshes.

    Does what ``dolfinx.io.gmsh.read_from_msh`` does (gmsh merges the file on
    rank 0, ``dolfinx.io.gmsh.model_to_mesh`` distributes it), after checking
    on rank 0 that the file is a mesh with cell and facet physical groups, so
    a bad file is an error message on every rank instead of a hang; gmsh's
    log is off and an already initialised gmsh session is left as it was.
    """
    import dolfinx.io.gmsh
    import gmsh

    info, err = None, None
    initialized = False
    if comm.rank == 0:
        initialized = gmsh.isInitialized()
        if not initialized:
            gmsh.initialize()
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("nagata-snap input")
        try:
            gmsh.merge(path)
            dim = gmsh.model.getDimension()
            groups = gmsh.model.getPhysicalGroups()
            _, xyz, _ = gmsh.model.mesh.getNodes()
            xyz = np.asarray(xyz).reshape(-1, 3)
            if dim not in (2, 3) or len(xyz) == 0:
                err = f"{path}: no 2D or 3D mesh found in the file"
            elif not any(d == dim for d, _ in groups):
                err = f"{path}: the cells are in no physical group (dolfinx needs cell physical groups)"
            elif not any(d == dim - 1 for d, _ in groups):
                err = (f"{path}: no facet tags (no physical groups of dimension {dim - 1}); "
                       "nothing can be snapped")
            else:
                scale = max(float(np.ptp(xyz, axis=0).max()), 1e-300)
                planar = dim == 2 and float(np.abs(xyz[:, 2]).max()) <= 1e-12 * scale
                info = (dim, 2 if planar else 3)
        except Exception as e:
            err = f"cannot read {path} as a gmsh mesh: {e}"
    try:
        dim, gdim = _bcast_checked(comm, info, err)
        try:
            data = dolfinx.io.gmsh.model_to_mesh(gmsh.model, comm, 0, gdim=gdim)
        except Exception as e:  # after the checks above this is unusual
            raise UserError(f"cannot read {path} as a gmsh mesh: {e}") from None
    finally:
        if comm.rank == 0:
            gmsh.model.remove()
            if not initialized:
                gmsh.finalize()
    if data.facet_tags is None:
        raise UserError(f"{path}: no facet tags could be read")
    return data.mesh, data.facet_tags


def _xdmf_grids(path: str) -> list[tuple[str, int]]:
    """(name, topological dimension) of every grid with a topology in an XDMF file."""
    root = ET.parse(path).getroot()
    grids = []
    for g in root.iter("Grid"):
        topo = g.find("Topology")
        if topo is None:
            continue
        ttype = (topo.get("TopologyType") or topo.get("Type") or "").lower()
        grids.append((g.get("Name") or "", _XDMF_DIM.get(ttype, -1)))
    return grids


def read_xdmf(path: str, comm, mesh_name: str | None, tag_name: str | None):
    """XDMF mesh + facet MeshTags -> (mesh, facet_tags)."""
    import dolfinx.io

    try:
        grids = _xdmf_grids(path)
    except (ET.ParseError, OSError) as e:
        raise UserError(f"cannot read {path} as XDMF: {e}") from None
    names = [n for n, _ in grids]
    if not grids:
        raise UserError(f"{path}: no grid with a topology in the XDMF file")
    if mesh_name is None:
        dims = dict(grids)
        mesh_name = "mesh" if "mesh" in dims else max(grids, key=lambda g: g[1])[0]
    elif mesh_name not in names:
        raise UserError(f"{path}: no grid named {mesh_name!r} (grids: {', '.join(names)})")
    tdim = dict(grids)[mesh_name]
    if tag_name is None:
        cand = [n for n, d in grids if d == tdim - 1 and n != mesh_name]
        if not cand:
            raise UserError(
                f"{path}: no facet tags (no grid of dimension {tdim - 1}; grids: {', '.join(names)})"
            )
        tag_name = cand[0]
    elif tag_name not in names:
        raise UserError(f"{path}: no grid named {tag_name!r} (grids: {', '.join(names)})")
    try:
        with dolfinx.io.XDMFFile(comm, path, "r") as f:
            mesh = f.read_mesh(name=mesh_name)
            mesh.topology.create_connectivity(mesh.topology.dim - 1, mesh.topology.dim)
            ft = f.read_meshtags(mesh, name=tag_name)
    except Exception as e:
        raise UserError(f"cannot read mesh {mesh_name!r} / tags {tag_name!r} from {path}: {e}") from None
    if ft.dim != mesh.topology.dim - 1:
        raise UserError(f"{path}: {tag_name!r} tags entities of dimension {ft.dim}, not facets")
    return mesh, ft


def read_meshio(path: str, comm, tag_key: str | None):
    """Any meshio format -> (mesh, facet_tags), built with ``dolfinx.mesh.create_mesh``."""
    import basix.ufl
    import dolfinx.graph
    import dolfinx.io
    import dolfinx.mesh
    import ufl

    payload, err = None, None
    if comm.rank == 0:
        try:
            payload = _meshio_arrays(path, tag_key)
        except UserError as e:
            err = str(e)
    tdim, gdim, _ = _bcast_checked(comm, None if payload is None else payload[:3], err)
    if comm.rank == 0:
        assert payload is not None  # else _bcast_checked raised rank 0's error
        _, _, _, x, cells, facets, values = payload
    else:
        x = np.zeros((0, gdim))
        cells = np.zeros((0, tdim + 1), dtype=np.int64)
        facets = np.zeros((0, tdim), dtype=np.int64)
        values = np.zeros(0, dtype=np.int32)
    cell = "triangle" if tdim == 2 else "tetrahedron"
    domain = ufl.Mesh(basix.ufl.element("Lagrange", cell, 1, shape=(gdim,)))
    try:
        mesh = dolfinx.mesh.create_mesh(comm, cells, domain, x)
    except Exception as e:
        raise UserError(f"{path}: cannot build a DOLFINx mesh: {e}") from None
    fdim = tdim - 1
    ents, vals = dolfinx.io.distribute_entity_data(mesh, fdim, facets, values)
    mesh.topology.create_connectivity(fdim, tdim)
    ft = dolfinx.mesh.meshtags_from_entities(
        mesh, fdim, dolfinx.graph.adjacencylist(ents), vals.astype(np.int32, copy=False)
    )
    ft.name = "facet_tags"
    return mesh, ft


def _meshio_arrays(path: str, tag_key: str | None):
    """Rank-0 part of :func:`read_meshio`: validated numpy arrays."""
    try:
        import meshio
    except ImportError:
        raise UserError("reading this format needs meshio (pip install meshio)") from None
    try:
        m = meshio.read(path)
    except Exception as e:
        raise UserError(f"cannot read {path} with meshio: {type(e).__name__}: {e}") from None
    types = [b.type for b in m.cells]
    if "tetra" in types:
        tdim, ctype, ftype = 3, "tetra", "triangle"
    elif "triangle" in types:
        tdim, ctype, ftype = 2, "triangle", "line"
    else:
        raise UserError(
            f"{path}: no linear triangle or tetrahedron cells (cell blocks: {', '.join(types) or 'none'})"
        )
    keys = sorted(m.cell_data)
    key = tag_key if tag_key is not None else "gmsh:physical"
    if key not in m.cell_data:
        if tag_key is None:
            raise UserError(
                f"{path}: no 'gmsh:physical' cell data for facet tags; name the key with --tag-key "
                f"(available cell data: {', '.join(keys) or 'none'})"
            )
        raise UserError(f"{path}: no cell data {key!r} (available cell data: {', '.join(keys) or 'none'})")
    cells = np.concatenate([np.asarray(b.data, dtype=np.int64) for b in m.cells if b.type == ctype])
    fblocks = [(b, np.asarray(d)) for b, d in zip(m.cells, m.cell_data[key], strict=True) if b.type == ftype]
    if not fblocks:
        raise UserError(f"{path}: no {ftype} facet cells carrying {key!r} tags")
    facets = np.concatenate([np.asarray(b.data, dtype=np.int64) for b, _ in fblocks])
    values = np.concatenate([d.reshape(-1) for _, d in fblocks])
    if not np.issubdtype(values.dtype, np.integer) and (
            not np.all(np.isfinite(values)) or np.any(values != np.round(values))):
        raise UserError(f"{path}: cell data {key!r} is not integer valued")
    values = values.astype(np.int32)
    pts = np.asarray(m.points, dtype=float)
    used, inv = np.unique(cells, return_inverse=True)
    lookup = np.full(len(pts), -1, dtype=np.int64)
    lookup[used] = np.arange(len(used))
    cells = inv.reshape(cells.shape)
    facets = lookup[facets]
    keep = np.all(facets >= 0, axis=1)  # facets of points no cell uses cannot be boundary facets
    facets, values = facets[keep], values[keep]
    x = pts[used]
    scale = max(float(np.ptp(x, axis=0).max()), 1e-300) if len(x) else 1.0
    if tdim == 3 and x.shape[1] < 3:
        raise UserError(f"{path}: tetrahedra need 3D points")
    if tdim == 2 and (x.shape[1] == 2 or float(np.abs(x[:, 2]).max()) <= 1e-12 * scale):
        gdim = 2
    else:
        gdim = 3
    x = np.ascontiguousarray(x[:, :gdim])
    return tdim, gdim, len(x), x, cells, facets, values


def read_mesh(path: str, comm, args):
    """Dispatch on the file extension."""
    if not os.path.isfile(path):
        raise UserError(f"input file {path} does not exist")
    ext = os.path.splitext(path)[1].lower()
    if ext == ".msh":
        return read_msh(path, comm)
    if ext == ".xdmf":
        return read_xdmf(path, comm, args.mesh_name, args.tag_name)
    return read_meshio(path, comm, args.tag_key)


# --------------------------------------------------------------------------
# output
# --------------------------------------------------------------------------
def write_mesh(path: str, mesh, facet_tags, comm) -> str:
    import dolfinx.io

    ext = os.path.splitext(path)[1].lower()
    if ext == ".xdmf":
        mesh.topology.create_connectivity(mesh.topology.dim - 1, mesh.topology.dim)
        mesh.name = "mesh"
        facet_tags.name = "facet_tags"
        with dolfinx.io.XDMFFile(comm, path, "w") as f:
            f.write_mesh(mesh)
            f.write_meshtags(facet_tags, mesh.geometry)
        return "mesh 'mesh' and facet tags 'facet_tags'"
    with dolfinx.io.VTXWriter(comm, path, mesh, engine="BP4") as w:
        w.write(0.0)
    return "mesh only (VTX cannot hold facet tags; use .xdmf for them)"


# --------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------
#: CAD file suffixes: such an input is meshed by gmsh
CAD_SUFFIXES = (".step", ".stp", ".igs", ".iges", ".brep", ".brp")
#: seconds between the heartbeat lines of a long level
HEARTBEAT = 10.0

#: :attr:`Snapper.stage` -> the heartbeat's words
_STAGES = {"refine": "refining (dolfinx.mesh.refine)", "lineage": "parent maps of the new facets",
           "place": "placing the new boundary vertices", "smooth+check": "smoothing and checking the cells",
           "tags": "facet tags", "report": "quality report"}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description=(
            "Refine a mesh uniformly with dolfinx.mesh.refine and snap the new boundary vertices "
            "onto the curved geometry.  A CAD file (STEP, IGES, BREP) is meshed by gmsh first and "
            "snapped onto its own faces; a mesh is snapped onto Nagata patches built from itself "
            "(default) or onto a CAD file (--cad)."
        ),
        epilog=(
            "Input: a CAD file (.step/.stp, .igs/.iges, .brep), gmsh .msh (facet tags = physical "
            "groups of dimension d-1), .xdmf (a mesh grid and a facet MeshTags grid), or any format "
            "meshio reads (linear triangles/tetrahedra; facet tags from cell data 'gmsh:physical' "
            "or --tag-key).  Exit status 0: done; 2: unusable input (file, format, tags, options); "
            "1: snapping failed (e.g. cells would invert)."
        ),
    )
    p.add_argument("input", help="CAD file (.step, .igs, .brep) or mesh file (.msh, .xdmf, meshio)")
    p.add_argument("--tags", type=int, nargs="+", metavar="TAG",
                   help="facet tag values whose facets are snapped (required for a mesh input; a CAD "
                        "input snaps every exterior face, tagged by its gmsh surface tag)")
    p.add_argument("--cad", "--iges", dest="cad", metavar="FILE",
                   help="mesh input, CAD mode: snap onto the faces (2D: edges) of this STEP, IGES or "
                        "BREP file instead of Nagata patches")
    p.add_argument("--size", type=float, metavar="H",
                   help="CAD input: largest element size of the coarse gmsh mesh (default: 0.1 of the "
                        "model's bounding-box diagonal)")
    p.add_argument("--curvature", type=float, default=12, metavar="N",
                   help="CAD input: gmsh elements per 2 pi of curvature (0: off; default 12)")
    p.add_argument("--unit", metavar="UNIT",
                   help="length unit of the CAD geometry: MM (CAD input default, as gmsh), M, INCH, ..., "
                        "or FILE (the file's own; --cad default)")
    p.add_argument("--levels", type=int, default=1, metavar="N",
                   help="number of uniform refinements (default: 1)")
    p.add_argument("--crease-angle", type=float, default=60.0, metavar="DEG",
                   help="Nagata mode: boundary ridges with a dihedral angle above DEG degrees "
                        "stay sharp (default: 60)")
    p.add_argument("--surface", choices=("nagata", "fitted"), default="nagata",
                   help="mesh input without --cad: the surface rebuilt from the coarse boundary, Nagata "
                        "patches (default) or high-order local fits (nagata_snap.FittedGeometry)")
    p.add_argument("--degree", type=int, default=4, metavar="P",
                   help="--surface fitted: polynomial degree of the local fits, 2 to 6 (default: 4)")
    p.add_argument("--output", "-o", metavar="OUT",
                   help="write the refined mesh: OUT.xdmf (mesh + facet tags, XDMF/HDF5) or "
                        "OUT.bp (mesh, VTX/ADIOS2); without it nothing is written")
    p.add_argument("--plot", metavar="FILE.png",
                   help="draw per level the histograms of the changed cells' minimum angle and mean "
                        "ratio and of the boundary vertices' distance from the CAD (matplotlib)")
    p.add_argument("--report", action="store_true",
                   help="print the snapper's full report of every level (timings, geometry "
                        "statistics)")
    inp = p.add_argument_group("mesh file input", "where a meshio or XDMF file keeps the facet tags")
    inp.add_argument("--tag-key", metavar="KEY", help="meshio: the cell data of the tags (default: gmsh:physical)")
    inp.add_argument("--mesh-name", metavar="NAME", help="XDMF: the mesh grid (default: 'mesh', else the highest dim.)")
    inp.add_argument("--tag-name", metavar="NAME", help="XDMF: the facet tags grid (default: the first of facet dim.)")
    p.add_argument("--quiet", "-q", action="store_true", help="print nothing but errors")
    return p


def _check_options(args) -> bool:
    """Validate options; returns whether the input is a CAD file."""
    if args.levels < 0:
        raise UserError("--levels must be >= 0")
    if args.surface == "fitted" and not 2 <= args.degree <= 6:
        raise UserError(f"--degree must be from 2 to 6 (the fits' polynomial degree), got {args.degree}")
    if args.output is not None:
        ext = os.path.splitext(args.output)[1].lower()
        if ext not in (".xdmf", ".bp"):
            raise UserError(f"--output must end in .xdmf or .bp, got {args.output}")
        parent = os.path.dirname(os.path.abspath(args.output))
        if not os.path.isdir(parent):
            raise UserError(f"output directory {parent} does not exist")
    if args.plot is not None and not args.plot.lower().endswith(".png"):
        raise UserError(f"--plot must end in .png, got {args.plot}")
    cad_input = os.path.splitext(args.input)[1].lower() in CAD_SUFFIXES
    if cad_input:
        if args.cad is not None:
            raise UserError("--cad applies to a mesh input; a CAD input is snapped onto itself")
        if args.size is not None and not args.size > 0:
            raise UserError("--size must be positive")
        if not os.path.isfile(args.input):
            raise UserError(f"input file {args.input} does not exist")
    else:
        if args.tags is None:
            raise UserError("--tags is required for a mesh input (the facet tags to snap)")
        if args.size is not None:
            raise UserError("--size applies to a CAD input (the mesh is given)")
        if args.cad is not None and not os.path.isfile(args.cad):
            raise UserError(f"CAD file {args.cad} does not exist")
    return cad_input


def _next_meshing_step(args: argparse.Namespace, sizes: Sequence[float]) -> str:
    """What to try when gmsh could not mesh the CAD input with any retry: the flags."""
    smaller = f"--size {min(sizes) / 2:.3g}" if sizes else "a smaller --size"
    curvature = "--curvature 0" if args.curvature > 0 else "--curvature 12"
    return (f"next, try {smaller} (or smaller), or {curvature}; or mesh the part yourself (gmsh) and "
            f"snap that mesh onto the file: {PROG} part.msh --tags ... --cad {args.input}")


def _cad_input(args: argparse.Namespace, comm: MPI.Comm, say: Callable[..., None]) -> _Input:
    """Mesh the CAD input with gmsh (with its retries); its geometry, facets matched to the faces."""
    from nagata_snap.cad import CadError, mesh_cad
    from nagata_snap.errors import MeshingError

    t0 = time.perf_counter()
    try:
        cm, geometry = mesh_cad(args.input, comm, unit=(args.unit or "MM").upper(), size=args.size,
                                curvature=args.curvature, on_retry=lambda line: say(f"{PROG}: {line}"))
    except MeshingError as e:
        raise UserError(f"{e}; {_next_meshing_step(args, e.sizes)}") from None
    except (CadError, ValueError, OSError) as e:  # the message names the file, or is given it
        raise UserError(str(e) if str(e).startswith(str(args.input)) else f"{args.input}: {e}") from None
    except RuntimeError as e:
        raise SnapFailure(f"meshing {args.input}: {e}") from None
    tdim = cm.mesh.topology.dim
    assert geometry.model is not None  # mesh_cad reads the file: the geometry has its model
    retried = f", {cm.meshed_with}" if cm.meshed_with else ""
    say(f"{PROG}: meshed {args.input} with gmsh (size {cm.size:.4g} {cm.unit or ''}{retried}): "
        f"{cm.mesh.topology.index_map(tdim).size_global} cells ({tdim}D); CAD "
        f"{geometry.model.summary()} ({time.perf_counter() - t0:.2f} s)")
    return cm.mesh, cm.facet_tags, geometry, geometry.tags


def _mesh_input(args: argparse.Namespace, comm: MPI.Comm, say: Callable[..., None]) -> _Input:
    """Read the mesh input; the geometry (CAD file or None for Nagata patches)."""
    t0 = time.perf_counter()
    mesh, ft = read_mesh(args.input, comm, args)
    from nagata_snap.mesh.boundary import present_tags

    tdim = mesh.topology.dim
    say(f"{PROG}: read {args.input}: {mesh.topology.index_map(tdim).size_global} cells ({tdim}D), "
        f"facet tags {tag_list(present_tags(ft, comm))} ({time.perf_counter() - t0:.2f} s)")
    if args.cad is None:
        return mesh, ft, None, args.tags
    from nagata_snap.cad import CadError, CadGeometry

    try:
        geometry = CadGeometry.from_file(args.cad, dim=tdim, unit=(args.unit or "FILE").upper(),
                                         comm=comm)
    except CadError as e:
        raise UserError(f"cannot use the CAD file {args.cad}: {e}") from None
    return mesh, ft, geometry, args.tags


class _Heartbeat:
    """Prints ``... level k: still running (t s, <stage>)`` every :data:`HEARTBEAT` seconds on rank 0.

    The stage is the snapper's :attr:`~nagata_snap.Snapper.stage`.  A stage that holds
    Python's lock (``dolfinx.mesh.refine`` on a large mesh) delays the next line."""

    def __init__(self, say, level: int, snapper):
        import threading

        self.say, self.level, self.snapper, self.t0 = say, level, snapper, time.perf_counter()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self.stop.wait(HEARTBEAT):
            stage = _STAGES.get(self.snapper.stage or "", "")
            self.say(f"{PROG}:   ... level {self.level}: still running "
                     f"({time.perf_counter() - self.t0:.0f} s{', ' + stage if stage else ''})")

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()


def _snapped_vertices(snapper) -> tuple[np.ndarray, np.ndarray]:
    """``(x (nf, nfv, 3), face (nf,))``: the vertices of this process's snapped boundary
    facets and the CAD face (entity) each facet's record names."""
    lv = snapper._level
    sel = np.flatnonzero(lv.snapped)
    return lv.mesh.geometry.x[lv.boundary.nodes[sel]], lv.records.root


def boundary_distance(snapper) -> np.ndarray:
    """Distance of each snapped boundary facet vertex from its CAD face (this process's facets).

    The vertex is projected onto its own face (:meth:`CadGeometry.project`,
    seeded by its record); a vertex moved only part of the way is that far off.
    """
    x, _ = _snapped_vertices(snapper)
    if len(x) == 0:
        return np.zeros(0)
    on, _ = snapper.geometry.project(snapper._level.records, x)
    return np.linalg.norm(on - x, axis=2).ravel()


def boundary_far(snapper, dist: np.ndarray, comm) -> tuple[int, int]:
    """``(far, within)`` over all processes: the snapped boundary facet vertices farther than
    :data:`~nagata_snap.cad.tolerance.FAR_RTOL` of the model size from their face (``dist``:
    :func:`boundary_distance`), and how many of them lie inside the tolerance tube of an edge
    or vertex of that face and no farther than its tolerance, or on both faces' surfaces of
    such an edge where they meet within its tolerance
    (:func:`~nagata_snap.cad.tolerance.count_far`: the file's faces meet only within it)."""
    from nagata_snap.cad.tolerance import count_far

    x, face = _snapped_vertices(snapper)
    geometry = snapper.geometry
    far, within = count_far(getattr(geometry, "model", None), np.repeat(face, x.shape[1]), x.reshape(-1, 3),
                            dist, geometry.size, meet=True)
    return comm.allreduce(far), comm.allreduce(within)


def _run(args, comm) -> None:
    say = (lambda *a: None) if args.quiet or comm.rank != 0 else (lambda *a: print(*a, flush=True))
    cad_input = _check_options(args)
    import nagata_snap
    from nagata_snap.mesh.boundary import check_snap_input

    mesh, ft, geometry, tags = (_cad_input if cad_input else _mesh_input)(args, comm, say)
    try:
        tags = check_snap_input(mesh, ft, tags)
    except ValueError as e:
        raise UserError(f"{args.input}: {e}") from None
    t0 = time.perf_counter()
    if geometry is not None and args.surface == "fitted":
        raise UserError("--surface fitted rebuilds the surface from a mesh input; a CAD input or --cad "
                        "snaps onto the CAD itself (drop --surface or the CAD)")
    if geometry is None and args.surface == "fitted":
        what = f"fitted surface of degree {args.degree} (crease angle {args.crease_angle} deg)"
    elif geometry is None:
        what = f"Nagata patches (crease angle {args.crease_angle} deg)"
    else:
        n = geometry.num_entities
        what = (f"{'faces' if geometry.param_dim == 2 else 'edge curves'} of "
                f"{args.input if cad_input else args.cad} ({n} {'entity' if n == 1 else 'entities'})")
    try:
        snap_geometry: SnapGeometry
        if geometry is not None:
            snap_geometry = geometry
        elif args.surface == "fitted":
            snap_geometry = nagata_snap.FittedGeometry(mesh, ft, tags=tags, crease_angle=args.crease_angle,
                                                       degree=args.degree)
        else:
            snap_geometry = nagata_snap.NagataGeometry(mesh, ft, tags=tags, crease_angle=args.crease_angle)
        snapper = nagata_snap.Snapper(mesh, ft, snap_geometry, tags=tags)
    except Exception as e:
        raise SnapFailure(f"cannot set up snapping of tags {tag_list(tags)}: {type(e).__name__}: {e}") from None
    say(f"{PROG}: snapping tags {tag_list(snapper.tags)} onto {what} ({time.perf_counter() - t0:.2f} s)")

    cad = geometry is not None  # CAD: distances from the faces are reported
    history = []
    for level in range(1, args.levels + 1):
        t0 = time.perf_counter()
        try:
            with _Heartbeat(say, level, snapper):
                mesh, ft, _, _, report = snapper.refine(mesh)
        except Exception as e:
            raise SnapFailure(f"level {level}: {type(e).__name__}: {e}") from None
        short = f", {report.shortfall_note()}" if report.partially_moved else ""
        say(f"{PROG}: level {level}/{args.levels}: {report.num_cells} cells, "
            f"{report.num_vertices} vertices, {report.boundary_vertices_moved} boundary vertices "
            f"snapped (max move {report.max_displacement:.3e}){short}, "
            f"{time.perf_counter() - t0:.2f} s")
        if args.report:
            say(f"  {report}")
            if report.geometry.n_points:
                say("  geometry: " + report.geometry.summary())
        dist = boundary_distance(snapper) if cad and (args.plot or level == args.levels) else None
        history.append((level, report, dist))
    far = boundary_far(snapper, history[-1][2], comm) if cad and history and history[-1][2] is not None else None
    _summary(say, comm, snapper, history, far)
    if args.plot is not None and history:
        t0 = time.perf_counter()
        everything = [(lv, rep, None if d is None else np.concatenate(comm.allgather(d)))
                      for lv, rep, d in history]
        if comm.rank == 0:
            try:
                plot_levels(args.plot, everything, snapper.geometry)
            except Exception as e:
                raise UserError(f"cannot write the plot {args.plot}: {type(e).__name__}: {e}") from None
        say(f"{PROG}: wrote {args.plot} ({time.perf_counter() - t0:.2f} s)")

    if args.output is not None:
        t0 = time.perf_counter()
        try:
            what = write_mesh(args.output, mesh, ft, comm)
        except Exception as e:
            raise UserError(f"cannot write {args.output}: {e}") from None
        say(f"{PROG}: wrote {args.output}: {what} ({time.perf_counter() - t0:.2f} s)")


def _summary(say, comm, snapper, history, far: tuple[int, int] | None) -> None:
    """Last line(s): vertices left short of the geometry, largest distance from the CAD
    (``far``: :func:`boundary_far` of the last level, None without a CAD)."""
    if not history:
        return
    level, report, dist = history[-1]
    short = sum(int(getattr(r, "partially_moved", 0) or 0) for _, r, _ in history)
    line = (f"{PROG}: summary: {level} level{'s' if level > 1 else ''}, {report.num_cells} cells; "
            f"{report.partially_moved} boundary vertices left short of the geometry in the last "
            f"level ({short} over all levels, max shortfall {report.max_shortfall:.3e})")
    if far is not None and dist is not None:
        dmax = comm.allreduce(float(dist.max(initial=0.0)), op=MPI.MAX)
        size = snapper.geometry.size
        off, within = far
        inside = f" ({within} of them inside the file's own edge tolerances)" if off else ""
        line += (f"; max distance of a boundary vertex from its CAD face {dmax:.3e} "
                 f"({dmax / size:.1e} of the model size; {off} farther than 1e-9 of it{inside})")
    say(line)


def plot_levels(path: str, history, geometry) -> None:
    """Histograms per level (:func:`level_figure`) written to ``path`` (PNG)."""
    import matplotlib.pyplot as plt

    fig = level_figure(history, geometry)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def level_figure(history, geometry):
    """Histograms per level: changed cells' min angle and mean ratio, boundary distance from the CAD.

    Args:
        history: ``(level, report, dist)`` per level; ``dist`` the boundary vertices'
            distances from the CAD (length units) or None.
        geometry: what ``dist`` is scaled by (``geometry.size``, the model size).

    Every count axis is logarithmic from half a vertex (or cell) up, so a few hundred
    vertices off the CAD among a million still show as a bar.  Returns the matplotlib figure (one row per level).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = 3 if any(d is not None for _, _, d in history) else 2
    fig, axes = plt.subplots(len(history), cols, figsize=(4 * cols, 2.6 * len(history)), squeeze=False)
    for row, (level, rep, dist) in zip(axes, history, strict=True):
        q = rep.quality
        for ax, name, title in ((row[0], "min_angle", "min angle (deg)"), (row[1], "mean_ratio", "mean ratio")):
            m = None if q is None else getattr(q, name)
            if m is not None:
                ax.stairs(m.hist, m.bins, fill=True)
                if m.hist.max(initial=0) > 0:
                    ax.set_yscale("log")
                    ax.set_ylim(bottom=0.5)
            ax.set_title(f"level {level}: {title}" + (f" ({q.scope} cells)" if q is not None else ""))
        if cols == 3:
            ax = row[2]
            if dist is not None and dist.size:
                rel = np.maximum(dist / geometry.size, 1e-18)
                ax.hist(np.log10(rel), bins=40)
                ax.set_yscale("log")
                ax.set_ylim(bottom=0.5)  # from below one vertex: autoscaling would start near the smallest bar
                ax.set_ylabel("vertices")
            ax.set_title(f"level {level}: log10 distance from CAD / size")
    fig.tight_layout()
    return fig


def main(argv=None) -> int:
    """Command line entry point; returns the exit status (see module docstring)."""
    args = build_parser().parse_args(argv)
    comm = MPI.COMM_WORLD
    try:
        _run(args, comm)
    except UserError as e:
        if comm.rank == 0:
            print(f"{PROG}: error: {e}", file=sys.stderr, flush=True)
        return 2
    except ImportError as e:  # an optional dependency (errors.missing_extra says which)
        if not str(e).startswith("nagata_snap needs"):
            raise
        if comm.rank == 0:
            print(f"{PROG}: error: {e}", file=sys.stderr, flush=True)
        return 2
    except SnapFailure as e:
        if comm.rank == 0:
            print(f"{PROG}: error: snapping failed: {e}", file=sys.stderr, flush=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
