"""Attach of this checkout against a git revision of it, side by side in one process.

The revision's ``nagata_snap`` is exported (``git archive``) into a temporary directory and
renamed ``nagata_snap_ref`` (:func:`read_vs_ref.export_ref`), so that both versions are
imported together.  For every part and format of ``meshes/parts.py`` asked for, the part is
meshed once by gmsh (this checkout's ``mesh_cad``, the sizes of ``cad_parts.MESH`` unless
``--mesh name:size_factor:curvature`` overrides them) and read once (this checkout's
``read_cad`` and ``CadModel.from_data``); both versions get that model (for the revision a
copy by ``pickle``, its classes mapped to the revision's modules, its NURBS tables derived
again by the revision's code: two builds of the model from
the same data, one per package, can differ in the last bits on some IGES parts), each makes
its ``CadGeometry.from_model`` and records the mesh hints by its own ``use_cad_mesh``.  Then:

* the outputs of both versions' ``attach`` (root and params) are compared bitwise, with the
  hints and by global search (hints removed);
* the hinted attach (``geo.attach(x, nodes=gids)``, as ``cad_parts.attach_timing``) of the
  two versions is timed interleaved, ``--rounds`` rounds of ``--calls`` calls each, and the
  best call of each is kept (wall time); ``--search`` times the global-search attach too
  (interleaved, ``--rounds // 4`` calls of each).

    python benchmarks/attach_vs_ref.py [--ref main] [--parts a,b] [--formats step,iges]
                                       [--mesh plate:0.01:16] [--rounds 20] [--calls 5] [--search]

Printed per part and format: distinct boundary vertices, the best hinted attach of the revision
and of this checkout [us per distinct vertex] and per call [ms], their ratio, and whether the
outputs are identical (``same``) or not (``DIFF``).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def main() -> None:
    sys.path[:0] = [HERE, ROOT, os.path.join(ROOT, "meshes")]
    from read_vs_ref import add_part_options, export_ref

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ref", default="main", help="git revision to compare with (default main)")
    add_part_options(ap)
    ap.add_argument("--mesh", default="", help="name:size_factor:curvature,... overriding cad_parts.MESH")
    ap.add_argument("--rounds", type=int, default=20)
    ap.add_argument("--calls", type=int, default=5, help="calls per version and round")
    ap.add_argument("--search", action="store_true", help="time the global-search attach too (best of --rounds)")
    args = ap.parse_args()
    sys.path.insert(0, export_ref(args.ref))
    out = os.fdopen(os.dup(1), "w")
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)  # OpenCASCADE's and gmsh's messages
    import gc
    import io
    import pickle

    import mpi4py.MPI as MPI  # (before DOLFINx, which the packages import)
    import nagata_snap_ref.cad as ref
    import nagata_snap_ref.cad.meshed as ref_meshed
    import nagata_snap_ref.cad.nurbs as ref_nurbs
    import numpy as np
    import parts
    from cad_parts import MESH

    import nagata_snap.cad as new
    import nagata_snap.cad.meshed as new_meshed
    from nagata_snap.cad.topology import CadModel
    from nagata_snap.cad.worker import read_cad
    from nagata_snap.meshing import mesh_cad_file

    class RefUnpickler(pickle.Unpickler):
        """Unpickles this checkout's objects as the revision's."""

        def find_class(self, module: str, name: str):
            if module.startswith("nagata_snap."):
                module = "nagata_snap_ref." + module[len("nagata_snap."):]
            return super().find_class(module, name)

    def as_ref(blob: bytes):
        """The pickled model as the revision's objects; its NURBS derive their own tables again
        (their layout may differ between the versions)."""
        model = RefUnpickler(io.BytesIO(blob)).load()
        for obj in gc.get_objects():
            if isinstance(obj, ref_nurbs.NurbsSurface | ref_nurbs.NurbsCurve):
                obj.__post_init__()
        return model

    sizes = dict(MESH)
    for item in filter(None, args.mesh.split(",")):
        name, sf, cu = item.split(":")
        sizes[name] = (float(sf), float(cu))

    def same(a, b) -> bool:
        return a.root.dtype == b.root.dtype and np.array_equal(a.root, b.root) and \
            a.params.shape == b.params.shape and a.params.tobytes() == b.params.tobytes()

    def best_of(f, calls: int) -> float:
        best = np.inf
        for _ in range(calls):
            t0 = time.perf_counter()
            f()
            best = min(best, time.perf_counter() - t0)
        return best

    tmp = tempfile.mkdtemp(prefix="attach_vs_ref_parts_")
    print(f"{'part':20s} {'format':9s} {'nv':>6s} {args.ref + ' us/v':>10s} {'this us/v':>10s} "
          f"{args.ref + ' ms':>8s} {'this ms':>8s} {'ratio':>6s}  outputs"
          + ("   search us/v ref, this" if args.search else ""), file=out, flush=True)
    for name in args.parts.split(","):
        for fmt in args.formats.split(","):
            f = fmt if fmt == "step" or parts.PARTS[name].iges_faces_solid else "iges_brep"
            path = str(parts.write_part(name, tmp, (f,))[f])
            sf, cu = sizes[name]
            cm = mesh_cad_file(path, MPI.COMM_SELF, size_factor=sf, curvature=cu)
            blob = pickle.dumps(CadModel.from_data(read_cad(path, unit=cm.unit or "MM", isolate=False)))
            new_geo = new.CadGeometry.from_model(pickle.loads(blob))
            ref_geo = ref.CadGeometry.from_model(as_ref(blob))
            new_meshed.use_cad_mesh(new_geo, cm)
            ref_meshed.use_cad_mesh(ref_geo, cm)
            gids = np.asarray(cm.mesh.geometry.input_global_indices, dtype=np.int64)[cm.facets.nodes]
            x = cm.mesh.geometry.x[cm.facets.nodes]
            nv = len(np.unique(gids))
            geos = {"ref": ref_geo, "this": new_geo}
            hinted = {k: g.attach(x, nodes=gids) for k, g in geos.items()}  # first calls: not timed
            hints = {k: g._hints for k, g in geos.items()}
            searched, t_search = {}, dict.fromkeys(geos, np.inf)
            for k, g in geos.items():
                g._hints = None
                searched[k] = g.attach(x, nodes=gids)
                g._hints = hints[k]
            for _ in range(max(args.rounds // 4, 1) if args.search else 0):
                for k, g in geos.items():
                    g._hints = None
                    t_search[k] = min(t_search[k], best_of(lambda g=g, x=x, gids=gids: g.attach(x, nodes=gids), 1))
                    g._hints = hints[k]
            ok = same(hinted["ref"], hinted["this"]) and same(searched["ref"], searched["this"])
            best = dict.fromkeys(geos, np.inf)
            for _ in range(args.rounds):
                for k, g in geos.items():
                    best[k] = min(best[k], best_of(lambda g=g, x=x, gids=gids: g.attach(x, nodes=gids), args.calls))
            r, t = best["ref"], best["this"]
            print(f"{name:20s} {f:9s} {nv:6d} {1e6 * r / nv:10.2f} {1e6 * t / nv:10.2f} {1e3 * r:8.3f} "
                  f"{1e3 * t:8.3f} {t / r:6.2f}  {'same' if ok else 'DIFF'}"
                  + (f"   {1e6 * t_search['ref'] / nv:8.2f} {1e6 * t_search['this'] / nv:8.2f}"
                     if args.search else ""), file=out, flush=True)


if __name__ == "__main__":
    main()
