"""``nagata-snap``: refine a mesh file uniformly and snap its curved boundary.

A thin command line around :class:`~nagata_snap.NagataGeometry`,
:class:`~nagata_snap.cad.CadGeometry` and :class:`~nagata_snap.Snapper`::

    nagata-snap mesh.msh --tags 4 --levels 2 --output fine.xdmf
    nagata-snap mesh.xdmf --tags 2 --iges part.igs --output fine.bp --report
    mpiexec -n 4 nagata-snap mesh.vtu --tag-key medit:ref --tags 3 --output fine.xdmf

(also ``python -m nagata_snap.cli``).  Input formats: gmsh ``.msh`` (read as
``dolfinx.io.gmsh.read_from_msh`` does; facet tags from the physical groups of
dimension d-1), ``.xdmf`` (``dolfinx.io.XDMFFile``: a mesh and a facet
MeshTags grid, e.g. as written by this command) and anything meshio reads
(linear triangles or tetrahedra; facet tags from the cell data
``gmsh:physical`` or the key given by ``--tag-key``).

Exit status: 0 on success, 2 for unusable input (missing or unreadable
files, unknown tags, bad options), 1 if snapping itself fails (e.g. cells
would invert); the reason is printed as ``nagata-snap: error: ...`` on
standard error.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import xml.etree.ElementTree as ET

import mpi4py.MPI as MPI

import numpy as np

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
def _bcast_checked(comm, value, error):
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
    import gmsh

    import dolfinx.io.gmsh

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
    import ufl

    import dolfinx.graph
    import dolfinx.io
    import dolfinx.mesh

    payload, err = None, None
    if comm.rank == 0:
        try:
            payload = _meshio_arrays(path, tag_key)
        except UserError as e:
            err = str(e)
    tdim, gdim, nvert = _bcast_checked(comm, None if payload is None else payload[:3], err)
    if comm.rank == 0:
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
    fblocks = [(b, np.asarray(d)) for b, d in zip(m.cells, m.cell_data[key]) if b.type == ftype]
    if not fblocks:
        raise UserError(f"{path}: no {ftype} facet cells carrying {key!r} tags")
    facets = np.concatenate([np.asarray(b.data, dtype=np.int64) for b, _ in fblocks])
    values = np.concatenate([d.reshape(-1) for _, d in fblocks])
    if not np.issubdtype(values.dtype, np.integer):
        if not np.all(np.isfinite(values)) or np.any(values != np.round(values)):
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
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description=(
            "Refine a mesh uniformly with dolfinx.mesh.refine and snap the new vertices of the "
            "facets with the given tags onto the curved geometry: Nagata patches built from "
            "the input mesh itself (default) or the NURBS of an IGES file (--iges)."
        ),
        epilog=(
            "Input: gmsh .msh (facet tags = physical groups of dimension d-1), .xdmf "
            "(a mesh grid and a facet MeshTags grid), or any format meshio reads (linear "
            "triangles/tetrahedra; facet tags from cell data 'gmsh:physical' or --tag-key).  "
            "Exit status 0: done; 2: unusable input (file, format, tags, options); 1: snapping "
            "failed (e.g. cells would invert)."
        ),
    )
    p.add_argument("input", help="mesh file: .msh, .xdmf or a meshio-readable format")
    p.add_argument("--tags", type=int, nargs="+", required=True, metavar="TAG",
                   help="facet tag values whose facets are snapped (required); other boundary "
                        "facets are refined with straight midpoints")
    p.add_argument("--iges", metavar="FILE",
                   help="CAD mode: snap onto the NURBS curves (2D) or surfaces (3D) of this IGES "
                        "file instead of Nagata patches")
    p.add_argument("--levels", type=int, default=1, metavar="N",
                   help="number of uniform refinements (default: 1)")
    p.add_argument("--crease-angle", type=float, default=60.0, metavar="DEG",
                   help="Nagata mode: boundary ridges with a dihedral angle above DEG degrees "
                        "stay sharp (default: 60)")
    p.add_argument("--output", "-o", metavar="OUT",
                   help="write the refined mesh: OUT.xdmf (mesh + facet tags, XDMF/HDF5) or "
                        "OUT.bp (mesh, VTX/ADIOS2); without it nothing is written")
    p.add_argument("--report", action="store_true",
                   help="print the snapper's full report of every level (timings, geometry "
                        "statistics)")
    p.add_argument("--tag-key", metavar="KEY",
                   help="meshio formats: cell data holding the facet tags (default: gmsh:physical)")
    p.add_argument("--mesh-name", metavar="NAME",
                   help="XDMF input: name of the mesh grid (default: 'mesh', else the grid of "
                        "highest dimension)")
    p.add_argument("--tag-name", metavar="NAME",
                   help="XDMF input: name of the facet tags grid (default: the first grid of "
                        "facet dimension)")
    p.add_argument("--quiet", "-q", action="store_true", help="print nothing but errors")
    return p


def _run(args, comm) -> None:
    say = (lambda *a: None) if args.quiet or comm.rank != 0 else (lambda *a: print(*a, flush=True))
    if args.levels < 0:
        raise UserError("--levels must be >= 0")
    if args.output is not None:
        ext = os.path.splitext(args.output)[1].lower()
        if ext not in (".xdmf", ".bp"):
            raise UserError(f"--output must end in .xdmf or .bp, got {args.output}")
        parent = os.path.dirname(os.path.abspath(args.output))
        if not os.path.isdir(parent):
            raise UserError(f"output directory {parent} does not exist")
    if args.iges is not None and not os.path.isfile(args.iges):
        raise UserError(f"IGES file {args.iges} does not exist")

    t0 = time.perf_counter()
    mesh, ft = read_mesh(args.input, comm, args)
    tdim = mesh.topology.dim
    if mesh.geometry.cmap.degree != 1 or tdim not in (2, 3):
        raise UserError(f"{args.input}: only affine triangle and tetrahedron meshes can be snapped")
    present = sorted(set(np.concatenate(comm.allgather(np.asarray(ft.values))).tolist()))
    missing = [t for t in args.tags if t not in present]
    if missing:
        raise UserError(
            f"facet tag{'s' if len(missing) > 1 else ''} {', '.join(map(str, missing))} not found in "
            f"{args.input}; available facet tags: {', '.join(map(str, present)) or 'none'}"
        )
    ncells = mesh.topology.index_map(tdim).size_global
    say(f"{PROG}: read {args.input}: {ncells} cells ({tdim}D), facet tags {present} "
        f"({time.perf_counter() - t0:.2f} s)")

    import nagata_snap

    t0 = time.perf_counter()
    if args.iges is not None:
        from .cad import CadGeometry

        try:
            geometry = CadGeometry.from_iges(args.iges, dim=tdim)
        except (OSError, ValueError) as e:
            raise UserError(f"cannot read IGES file {args.iges}: {e}") from None
        except Exception as e:  # CadError: no entities of the needed kind
            raise UserError(f"{args.iges}: {e}") from None
        n = geometry.num_entities
        what = f"IGES {args.iges} ({n} NURBS {'entity' if n == 1 else 'entities'})"
    else:
        geometry = None
        what = f"Nagata patches (crease angle {args.crease_angle} deg)"
    try:
        if geometry is None:
            geometry = nagata_snap.NagataGeometry(mesh, ft, tags=args.tags,
                                                  crease_angle=args.crease_angle)
        snapper = nagata_snap.Snapper(mesh, ft, geometry, tags=args.tags)
    except Exception as e:
        raise SnapFailure(f"cannot set up snapping of tags {args.tags}: {type(e).__name__}: {e}") from None
    say(f"{PROG}: snapping tags {args.tags} onto {what} ({time.perf_counter() - t0:.2f} s)")

    for level in range(1, args.levels + 1):
        t0 = time.perf_counter()
        try:
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
            if report.geometry:
                say("  geometry: " + ", ".join(f"{k} {v}" for k, v in report.geometry.items()))

    if args.output is not None:
        t0 = time.perf_counter()
        try:
            what = write_mesh(args.output, mesh, ft, comm)
        except Exception as e:
            raise UserError(f"cannot write {args.output}: {e}") from None
        say(f"{PROG}: wrote {args.output}: {what} ({time.perf_counter() - t0:.2f} s)")


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
    except SnapFailure as e:
        if comm.rank == 0:
            print(f"{PROG}: error: snapping failed: {e}", file=sys.stderr, flush=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
