"""Write the project's IGES test files into ``meshes/`` (deterministically).

Files:

* ``kadir_circle.igs``, ``kadir_cylinder.igs``: Kadir (2010), Appendix C
  (seed 003), "IGES File 1 2D Cylinder" (entity 126, the circle of centre
  (0.2, 0.2, 0) and radius 0.05) and "IGES File 2 3D Cylinder" (entity 128,
  centre (0.55, 0.5), z in [0, 0.4], radius 0.05).  The Start, Global and
  Parameter data lines are transcribed as printed (same P line breaks, the
  weights rounded to ``0.707107``, the Global section with its unit flag one
  field late, the cylinder's ``0,0,0,0`` parameter range); the 80-column
  layout, which the thesis' text lost, is rebuilt: DE fields right-justified
  in 8 columns, the parameter line count (DE field 14) set to the number of
  printed P lines, the sequence numbers zero-padded.
* ``occ_sphere.igs``, ``occ_torus.igs``, ``occ_part.igs``: written by gmsh's
  OpenCASCADE kernel (``gmsh.write``) for a unit sphere, a torus (R=1,
  r=0.3) and a unit box minus a cylinder of radius 0.2 through it.  OCC
  writes them with entities 144/142/120/108/102/110/100/124/402.  The date
  and author in the Global section are replaced by fixed values so the files
  do not depend on when or by whom they were made.
* ``dfg_circle.igs``: the DFG benchmark cylinder, circle of radius 0.05 at
  (0.2, 0.2, 0), as an exact rational quadratic NURBS (entity 126, weights
  ``sqrt(2)/2``) written by :func:`nagata_snap.cad.iges.write_iges`.

Run ``python meshes/make_iges.py [outdir]``.
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
if str(HERE.parent) not in sys.path:
    sys.path.insert(0, str(HERE.parent))

from nagata_snap.cad.iges import _pack, write_iges  # noqa: E402
from nagata_snap.cad.nurbs import NurbsCurve  # noqa: E402

FIXED_DATE = "20000101.000000"

# ----------------------------------------------------------------------
# Kadir (2010), Appendix C: parameter data as printed
# ----------------------------------------------------------------------
KADIR_CIRCLE_START = [
    "Description: Circle / Cylinder cross section (2D), NURBS",
    "Center = (0.2, 0.2, 0.0), Radius = 0.05",
]
KADIR_CYLINDER_START = [
    "Description: Cylinder (3D), NURBS",
    "Center(x,y)=(0.55, 0.5), zmin=0, zmax=0.4, Radius=0.05",
]
KADIR_GLOBAL = "1H,,1H;,,,,,,,,,,,,,1,4HINCH,,,,,,,,,,,,;"

KADIR_CIRCLE_P = [
    "126,",
    "8,2,",
    "1,1,0,0,",
    "0.0,0.0,0.0,0.25,0.25,0.5,0.5,0.75,0.75,1.0,1.0,1.0,",
    "1.0,0.707107,1.0,0.707107,1.0,0.707107,1.0,0.707107,1.0,",
    "0.25,0.2,0.0,",
    "0.25,0.25,0.0,",
    "0.2,0.25,0.0,",
    "0.15,0.25,0.0,",
    "0.15,0.2,0.0,",
    "0.15,0.15,0.0,",
    "0.2,0.15,0.0,",
    "0.25,0.15,0.0,",
    "0.25,0.2,0.0,",
    "0.0,1.0,",
    "0.0,0.0,1.0;",
]

KADIR_CYLINDER_P = [
    "128,",
    "8,1,2,1,",
    "1,0,0,0,0,",
    "0.0,0.0,0.0,0.25,0.25,0.5,0.5,0.75,0.75,1.0,1.0,1.0,",
    "0,0,1,1,",
    "1.0,0.707107,1.0,0.707107,1.0,0.707107,1.0,0.707107,1.0,",
    "1.0,0.707107,1.0,0.707107,1.0,0.707107,1.0,0.707107,1.0,",
    "0.60,0.5,0.0,",
    "0.6,0.55,0.0,",
    "0.55,0.55,0.0,",
    "0.50,0.55,0.0,",
    "0.50,0.5,0.0,",
    "0.50,0.45,0.0,",
    "0.55,0.45,0.0,",
    "0.6,0.45,0.0,",
    "0.60,0.5,0.0,",
    "0.60,0.5,0.4,",
    "0.6,0.55,0.4,",
    "0.55,0.55,0.4,",
    "0.50,0.55,0.4,",
    "0.50,0.5,0.4,",
    "0.50,0.45,0.4,",
    "0.55,0.45,0.4,",
    "0.6,0.45,0.4,",
    "0.60,0.5,0.4,",
    "0.0,0.0,0.0,0.0,0.0;",
]


def single_entity_file(start: list[str], global_line: str, etype: int, form: int,
                       plines: list[str]) -> str:
    """An 80-column IGES file with one entity whose P lines are given verbatim.

    Args:
        start: Start-section lines.
        global_line: Global-section data (one line, at most 72 characters).
        etype, form: entity type and form number for the directory entry.
        plines: parameter-data lines (at most 64 characters each).
    """
    out = [f"{s:<72s}S{k:07d}" for k, s in enumerate(start, 1)]
    out.append(f"{global_line:<72s}G{1:07d}")
    de = 1
    zeros = "00000000"
    out.append(f"{etype:8d}{1:8d}{0:8d}{0:8d}{0:8d}{0:8d}{0:8d}{0:8d}{zeros}D{1:07d}")
    out.append(f"{etype:8d}{0:8d}{0:8d}{len(plines):8d}{form:8d}{'':8s}{'':8s}{'':8s}{0:8d}D{2:07d}")
    for k, s in enumerate(plines, 1):
        out.append(f"{s:<64s} {de:7d}P{k:07d}")
    out.append(f"S{len(start):7d}G{1:7d}D{2:7d}P{len(plines):7d}".ljust(72) + "T0000001")
    assert all(len(s) == 80 for s in out)
    return "\n".join(out) + "\n"


#: Corner weight of the quarter arcs as printed in Kadir's files (not 1/sqrt 2).
KADIR_WEIGHT = 0.707107


def weight_rounding_error(w: float) -> float:
    """Relative radial error at the middle of a quarter arc with corner weight ``w``.

    Unit quarter circle P0=(1,0), P1=(1,1), P2=(0,1): C(1/2) = (P0 + 2 w P1 + P2) / (2 + 2 w),
    |C(1/2)| = sqrt(2) (1 + 2 w) / (2 + 2 w) (= 1 for w = 1/sqrt(2)).  This is the largest
    deviation of the arc (it is symmetric and monotone in each half), so Kadir's circle and
    cylinder are up to ``R * weight_rounding_error(KADIR_WEIGHT)`` off the exact ones.
    """
    return abs(math.sqrt(2.0) * (1 + 2 * w) / (2 + 2 * w) - 1.0)


def kadir_circle_text() -> str:
    """Kadir (2010) App. C, IGES File 1 (entity 126) in 80-column layout."""
    return single_entity_file(KADIR_CIRCLE_START, KADIR_GLOBAL, 126, 0, KADIR_CIRCLE_P)


def kadir_cylinder_text() -> str:
    """Kadir (2010) App. C, IGES File 2 (entity 128) in 80-column layout."""
    return single_entity_file(KADIR_CYLINDER_START, KADIR_GLOBAL, 128, 0, KADIR_CYLINDER_P)


# ----------------------------------------------------------------------
# exact circle (DFG cylinder)
# ----------------------------------------------------------------------
def circle_curve(center=(0.2, 0.2, 0.0), radius: float = 0.05) -> NurbsCurve:
    """Full circle in the plane z = center[2] as a 9-point rational quadratic NURBS.

    Same layout as Kadir's circle (knots ``0,0,0,1/4,1/4,1/2,1/2,3/4,3/4,1,1,1``,
    square control polygon) but with the exact corner weight ``sqrt(2)/2``
    (Piegl & Tiller 1997, sec. 7.5).
    """
    c = np.asarray(center, dtype=float)
    sq = np.array([[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1], [0, -1], [1, -1], [1, 0]], float)
    P = np.column_stack([c[0] + radius * sq[:, 0], c[1] + radius * sq[:, 1], np.full(9, c[2])])
    w = np.ones(9)
    w[1::2] = math.sqrt(0.5)
    U = np.array([0, 0, 0, 0.25, 0.25, 0.5, 0.5, 0.75, 0.75, 1, 1, 1], float)
    return NurbsCurve(degree=2, knots=U, control_points=P, weights=w)


# ----------------------------------------------------------------------
# files written by OpenCASCADE through gmsh
# ----------------------------------------------------------------------
def _global_tokens(data: str, pd: str, rd: str) -> list:
    """Tokens of an IGES Global section: Hollerith strings as ``(str,)``, others as ``str``."""
    toks, i = [], 0
    while i < len(data):
        m = re.match(r"\s*(\d+)H", data[i:])
        if m:  # Hollerith nHxxx: n characters, then a delimiter
            n = int(m.group(1))
            j = i + m.end()
            toks.append((data[j:j + n],))
            i = j + n
            i = data.index(pd, i) + 1 if data.find(rd, i) > data.find(pd, i) >= 0 else len(data)
            continue
        k = min([x for x in (data.find(pd, i), data.find(rd, i)) if x >= 0] or [len(data)])
        toks.append(data[i:k].strip())
        if k < len(data) and data[k] == rd:
            break
        i = k + 1
    return toks


def _fix_global(text: str) -> str:
    """Replace the date (Global 18, 25) and author (21) of an IGES text by fixed values."""
    lines = text.splitlines()
    g_idx = [i for i, s in enumerate(lines) if len(s) >= 73 and s[72] == "G"]
    data = "".join(lines[i][:72].ljust(72) for i in g_idx)
    m = re.match(r"\s*1H(.),", data)
    pd = m.group(1) if m else ","
    m2 = re.match(r"\s*(?:1H.)?" + re.escape(pd) + r"\s*1H(.)", data)
    rd = m2.group(1) if m2 else ";"
    out = []
    for k, t in enumerate(_global_tokens(data, pd, rd), start=1):
        if isinstance(t, tuple):  # Hollerith
            s = t[0]
            if k in (18, 25):
                s = FIXED_DATE
            elif k == 21:
                s = "nagata_snap"
            out.append(f"{len(s)}H{s}")
        else:
            out.append(t)
    # parameters 1-2 (delimiters) are written explicitly
    out[0], out[1] = f"1H{pd}", f"1H{rd}"
    glines = _pack(out, 72, pd, rd)
    new = [f"{s:<72s}G{k:07d}" for k, s in enumerate(glines, 1)]
    head = lines[:g_idx[0]]
    tail = lines[g_idx[-1] + 1:]
    t = tail[-1]
    tail[-1] = t[:8] + f"G{len(new):7d}" + t[16:]
    return "\n".join(head + new + tail) + "\n"


def write_occ_models(outdir: str | Path = HERE) -> list[Path]:
    """Write ``occ_sphere.igs``, ``occ_torus.igs`` and ``occ_part.igs`` with gmsh/OCC.

    Models: unit sphere at the origin; torus centre (0,0,0), R=1, r=0.3, axis
    z; unit box [0,1]^3 minus the cylinder of radius 0.2 on the axis
    (0.5, 0.5, z), z in [-0.1, 1.1] (6 planes, one of revolution, two holes).
    gmsh is initialised if needed and left as found.
    """
    import gmsh

    occ = gmsh.model.occ
    models = {
        "occ_sphere.igs": lambda: occ.addSphere(0, 0, 0, 1),
        "occ_torus.igs": lambda: occ.addTorus(0, 0, 0, 1, 0.3),
        "occ_part.igs": lambda: occ.cut([(3, occ.addBox(0, 0, 0, 1, 1, 1))],
                                        [(3, occ.addCylinder(0.5, 0.5, -0.1, 0, 0, 1.2, 0.2))]),
    }
    return [_write_occ_iges(Path(outdir) / name, name, build) for name, build in models.items()]


def _write_occ_iges(path: Path, model: str, build: Callable[[], object]) -> Path:
    """Write what ``build()`` makes with ``gmsh.model.occ`` (in a fresh gmsh model named
    ``model``, gmsh left as found) as the IGES file ``path``, date and author fixed."""
    import gmsh

    from nagata_snap.meshing import gmsh_session

    path.parent.mkdir(parents=True, exist_ok=True)
    with gmsh_session(model, {"General.Terminal": 0}):
        build()
        gmsh.model.occ.synchronize()
        gmsh.write(str(path))
    path.write_text(_fix_global(path.read_text()), newline="\n")
    return path


#: the features part of :func:`build_occ_features`: a slab [0,1]x[0,1]x[0,0.5] with
#: a spherical dome, a countersunk hole and a toroidal groove
OCC_FEATURES = {
    "box": (0.0, 0.0, 0.0, 1.0, 1.0, 0.5),
    "dome": (0.7, 0.5, 0.35, 0.25),  # sphere centre, radius: the cap above z = 0.5
    "hole": (0.25, 0.5, -0.1, 0.0, 0.0, 0.7, 0.12),  # cylinder base, axis, radius
    "sink": (0.25, 0.5, 0.35, 0.0, 0.0, 0.2, 0.0, 0.25),  # cone base, axis, radii
    "groove": (0.7, 0.5, 0.0, 0.17, 0.06),  # torus centre, R, r: half of it cut from the bottom
}


def build_occ_features() -> list[int]:
    """Build the features part in the current gmsh model (OCC kernel); returns its volume tags.

    The slab ``[0,1] x [0,1] x [0,0.5]`` fused with a sphere of radius 0.25 at
    (0.7, 0.5, 0.35) (a partial sphere face above the top), minus a hole of
    radius 0.12 at (0.25, 0.5) with a conical countersink (radius 0.25 at the
    top, a partial cone face) and minus a torus (R = 0.17, r = 0.06) centred
    on the bottom face (half a torus face, a groove).  11 faces: 7 planes
    (the top with two holes, the bottom with one, the disk inside the groove)
    and partial sphere, cone, cylinder and torus faces; edges are circles
    shared by curved faces and planes or by two curved faces (cone/cylinder).
    """
    import gmsh

    occ = gmsh.model.occ
    f = OCC_FEATURES
    box = occ.addBox(*f["box"])
    dome = occ.addSphere(*f["dome"])
    hole = occ.addCylinder(*f["hole"])
    sink = occ.addCone(*f["sink"])
    groove = occ.addTorus(*f["groove"])
    out, _ = occ.fuse([(3, box)], [(3, dome)])
    out, _ = occ.cut(out, [(3, hole), (3, sink), (3, groove)])
    occ.synchronize()
    return [t for d, t in out if d == 3]


def write_occ_features(outdir: str | Path = HERE) -> Path:
    """Write ``occ_features.igs`` (:func:`build_occ_features`) with gmsh/OCC.

    Not part of :func:`write_all`: tests write it where they need it.  gmsh is
    initialised if needed and left as found.
    """
    return _write_occ_iges(Path(outdir) / "occ_features.igs", "occ_features", build_occ_features)


def write_kadir(outdir: str | Path = HERE) -> list[Path]:
    """Write ``kadir_circle.igs`` and ``kadir_cylinder.igs``."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    out = []
    for name, text in (("kadir_circle.igs", kadir_circle_text()),
                       ("kadir_cylinder.igs", kadir_cylinder_text())):
        (outdir / name).write_text(text, newline="\n")
        out.append(outdir / name)
    return out


def write_dfg_circle(outdir: str | Path = HERE) -> Path:
    """Write ``dfg_circle.igs``: circle radius 0.05 at (0.2, 0.2, 0), units M."""
    path = Path(outdir) / "dfg_circle.igs"
    write_iges(path, curves=[circle_curve((0.2, 0.2, 0.0), 0.05)], units="M",
               description="DFG benchmark cylinder: circle centre (0.2, 0.2, 0), radius 0.05")
    return path


def write_all(outdir: str | Path = HERE) -> list[Path]:
    """Write every file listed in the module docstring; returns their paths."""
    return [*write_kadir(outdir), write_dfg_circle(outdir), *write_occ_models(outdir)]


if __name__ == "__main__":
    for p in write_all(sys.argv[1] if len(sys.argv) > 1 else HERE):
        print(p)
