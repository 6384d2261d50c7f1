"""Does this checkout read CAD files to the same bits as a git revision?  (For changes meant
to be pure speed-ups of the read path.)

    python benchmarks/read_same.py [--ref main] [--parts a,b]

The revision's package is exported beside this one (as ``read_vs_ref.py`` does).  For every
part of ``meshes/parts.py`` written as STEP, BREP, B-rep IGES and faces-only IGES (the latter
also read with ``sew=False``), both versions' ``read_shape`` dict, ``CadModel.from_data`` model
and ``CadGeometry.from_model`` geometry are flattened into ``(path, token)`` pairs (every
attribute reached from them; arrays by dtype, shape and bytes; floats by ``float.hex``; the
``times`` skipped), with ``closest_point`` of 200 fixed random points in the model's box, and
compared.  Prints ``same`` or ``DIFF`` (with the first differing path) per case; exits 1 on
any difference.
"""

from __future__ import annotations

import argparse
import functools
import os
import re
import sys
import tempfile
import types

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
from read_vs_ref import export_ref  # noqa: E402

#: attributes left out: timings, the file's path (temporary directories), back references
SKIP = {"times", "path", "_sampler", "_lock"}
_FUNCTIONS = (types.FunctionType, types.MethodType, types.BuiltinFunctionType, functools.partial)


def flat(x) -> list[tuple[str, object]]:
    """``x`` flattened into ``(path, token)`` pairs, depth first (an object seen before: a
    reference to its first path)."""
    out: list[tuple[str, object]] = []
    _walk(x, out, {}, "", 0)
    return out


def _walk(x, out: list, seen: dict, at: str, depth: int) -> None:
    if depth > 12:
        return
    if isinstance(x, np.ndarray):
        out.append((at, (x.dtype.str, x.shape, x.tobytes() if x.dtype != object else repr(x))))
    elif isinstance(x, (bool, int, str, bytes, type(None), np.integer, np.bool_)):
        out.append((at, repr(x)))
    elif isinstance(x, (float, np.floating)):
        out.append((at, float(x).hex()))
    elif isinstance(x, _FUNCTIONS):
        out.append((at, getattr(x, "__qualname__", type(x).__name__)))
    elif id(x) in seen:
        out.append((at, "ref" + seen[id(x)]))
    else:
        seen[id(x)] = at
        _walk_container(x, out, seen, at, depth)


def _walk_container(x, out: list, seen: dict, at: str, depth: int) -> None:
    if isinstance(x, dict):
        for k in sorted(x, key=repr):
            if k not in SKIP:
                _walk(x[k], out, seen, f"{at}[{k!r}]", depth + 1)
    elif isinstance(x, (list, tuple)):
        out.append((at, f"len{len(x)}"))
        for i, v in enumerate(x):
            _walk(v, out, seen, f"{at}[{i}]", depth + 1)
    elif not type(x).__module__.startswith("OCP"):
        fields = dict(vars(x)) if hasattr(x, "__dict__") else {}
        fields.update({s: getattr(x, s) for s in getattr(type(x), "__slots__", ()) if hasattr(x, s)})
        if fields:
            out.append((at, type(x).__name__))
            for k in sorted(fields):
                if k not in SKIP:
                    _walk(fields[k], out, seen, f"{at}.{k}", depth + 1)
        else:  # addresses and the revision's package name left out
            text = re.sub(r"0x[0-9a-f]+", "", repr(x)[:200]).replace("nagata_snap_ref", "nagata_snap")
            out.append((at, f"{type(x).__name__}:{text}"))


def _read(pkg, path: str, kw: dict) -> list:
    """Everything the package ``pkg`` (``nagata_snap`` or the revision's) makes of ``path``, flat."""
    try:
        d = pkg.read.read_shape(path, **kw)
        m = pkg.topology.CadModel.from_data(d)
        g = pkg.CadGeometry.from_model(m)
        lo, hi = m.vertices.min(0), m.vertices.max(0)
        pts = lo + (hi - lo) * np.random.default_rng(0).random((200, 3))
        try:
            cp = g.closest_point(pts)
        except Exception as err:
            cp = repr(err)
        return flat({"data": d, "model": m, "geo": g, "cp": cp})
    except Exception as err:
        return [("error", repr(err))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ref", default="main", help="git revision to compare with (default main)")
    ap.add_argument("--parts", default=None, help="parts of meshes/parts.py (default: all)")
    args = ap.parse_args()
    sys.path[:0] = [export_ref(args.ref), ROOT, os.path.join(ROOT, "meshes")]
    out = os.fdopen(os.dup(1), "w")
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)  # OpenCASCADE's messages on reading IGES
    import mpi4py.MPI  # noqa: F401  (before DOLFINx, which the packages import)
    import parts

    import nagata_snap.cad as new
    import nagata_snap.cad.read
    import nagata_snap.cad.topology  # noqa: F401
    import nagata_snap_ref.cad as ref
    import nagata_snap_ref.cad.read
    import nagata_snap_ref.cad.topology  # noqa: F401

    tmp = tempfile.mkdtemp(prefix="read_same_")
    bad = 0
    for name in args.parts.split(",") if args.parts else list(parts.PARTS):
        for fmt, path in parts.write_part(name, tmp, ("step", "brep", "iges_brep", "iges")).items():
            for kw in ({}, {"sew": False}) if fmt == "iges" else ({},):
                a, b = _read(ref, str(path), kw), _read(new, str(path), kw)
                if a == b:
                    print(f"same {name} {fmt} {kw} ({len(a)} items)", file=out, flush=True)
                    continue
                bad += 1
                i = next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), min(len(a), len(b)))
                where = a[i][0] if i < len(a) else b[i][0]
                print(f"DIFF {name} {fmt} {kw}: {len(a)} vs {len(b)} items, first at {where}", file=out, flush=True)
    print("DIFFERENCES:", bad, file=out)
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
