"""The machined-part library (meshes/parts.py): every part is a valid solid (or planar face),
written as STEP, IGES and BREP by gmsh's OpenCASCADE, and read back the same.

Truth: OpenCASCADE's own shape checker (``BRepCheck_Analyzer`` through OCP, on
the BREP file), closed-form volumes and areas for the parts that have one, and
gmsh's ``occ.getMass`` of the model built in memory (for the round trips).
"""

from __future__ import annotations

import math

import gmsh
import pytest

import parts  # meshes/ is on sys.path (conftest.py)
from nagata_snap.meshing import gmsh_session, import_cad

FORMATS = ("step", "iges", "brep", "iges_brep")

#: closed-form volume (area for planar parts) [mm^3 / mm^2]
EXACT = {
    # 100 x 60 x 12 - 4 holes r 4 - 2 counterbore rings (r 8 - r 4, 5 deep) - 40 x 20 x 6 pocket
    "plate": 100 * 60 * 12 - 4 * math.pi * 16 * 12 - 2 * math.pi * (64 - 16) * 5 - 40 * 20 * 6,
    # cap of a sphere through (0, -8) and (25, 0) centred on the axis, height 8;
    # cylinder r 25, 40 high; minus the groove (half disk r 5 at radius 25,
    # Pappus); cone r 25, 30 high
    "revolved": (lambda R: math.pi * 64 * (3 * R - 8) / 3)((625 - 64) / 16 + 8)
    + math.pi * 625 * 40 - 2 * math.pi * (25 - 20 / (3 * math.pi)) * (math.pi * 25 / 2)
    + math.pi * 625 * 30 / 3,
    "concave_cylinder": 60 * 40 * 30 - math.pi * 100 / 2 * 60,
    "thin_wall": math.pi / 4 * (50**2 - 48.5**2) * 40,
    "assembly": 40 * 30 * 20 + math.pi * 64 * 15,
    # L (60 x 15 + 15 x 25) x 25 plus the fillet's material r^2 (1 - pi/4) x 25
    "reentrant_fillet": (60 * 15 + 15 * 25) * 25 + 25 * (1 - math.pi / 4) * 25,
    # 100 x 60 with r 6 corners, minus circles r 8, 5, 5 and a 16 x 10 slot with r 5 ends
    "plate_holes_2d": 6000 - 4 * (36 - math.pi * 36 / 4) - math.pi * (64 + 25 + 25)
    - (16 * 10 + math.pi * 25),
}

#: faces (3D) / curves (2D) of each part, counted from its construction
FACES = {
    "profile_2d": 8, "plate_holes_2d": 15,
    "box_fillet_chamfer": 18,  # 6 sides + 4 fillets + 4 chamfer planes + 4 chamfer cones
    "plate": 19, "revolved": 5, "extruded_bspline": 4, "lofted_blade": 3,
    "crossing_cylinders": 7, "seamed": 6, "assembly": 9, "plate_filleted": 35,
    "thin_wall": 6, "concave_cylinder": 8, "reentrant_fillet": 9,
}


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("parts")
    return {name: parts.write_part(name, out, FORMATS) for name in parts.PARTS}


def test_registry():
    assert set(FACES) == set(parts.PARTS)
    assert {p.dim for p in parts.PARTS.values()} == {2, 3}
    for p in parts.PARTS.values():
        assert p.description and p.features and p.issues
    with pytest.raises(KeyError, match="unknown part 'nope'"):
        parts.model_size("nope")
    with pytest.raises(ValueError, match="unknown formats"):
        parts.write_part("plate", "/tmp", ("stl",))


@pytest.mark.parametrize("name", list(parts.PARTS))
def test_part_builds(name):
    part = parts.PARTS[name]
    with parts.part_model(name):
        faces, mass = parts.measure(part.dim)
        n_solids = len(gmsh.model.getEntities(3))
        loose = [e for d in range(part.dim) for e in gmsh.model.getEntities(d)
                 if len(gmsh.model.getAdjacencies(*e)[0]) == 0]
        z = gmsh.model.getBoundingBox(-1, -1)
    assert faces == FACES[name]
    assert n_solids == (0 if part.dim == 2 else 2 if name == "assembly" else 1)
    assert not loose  # no construction points left over
    if part.dim == 2:
        assert max(abs(z[2]), abs(z[5])) < 1e-6  # in the plane z = 0
    if name in EXACT:
        assert mass == pytest.approx(EXACT[name], rel=1e-9)
    assert parts.model_size(name) == pytest.approx(math.dist(z[:3], z[3:]))


@pytest.mark.parametrize("name", list(parts.PARTS))
def test_part_valid_in_occ(written, name):
    """OpenCASCADE's checker accepts the shape; its adaptive volume (area) is the closed form's
    where there is one, and near gmsh's fixed-order one elsewhere (except on the loft)."""
    from OCP.BRep import BRep_Builder
    from OCP.BRepCheck import BRepCheck_Analyzer
    from OCP.BRepTools import BRepTools
    from OCP.TopoDS import TopoDS_Shape

    shape = TopoDS_Shape()
    assert BRepTools.Read_s(shape, str(written[name]["brep"]), BRep_Builder())
    assert BRepCheck_Analyzer(shape).IsValid()
    dim = parts.PARTS[name].dim
    mass = parts.occ_mass(written[name]["brep"], dim)
    if name in EXACT:
        assert mass == pytest.approx(EXACT[name], rel=1e-9)
    with parts.part_model(name):
        _, gmsh_mass = parts.measure(dim)
    if name == "lofted_blade":  # fixed-order Gauss integration is 17 % low here (see parts.occ_mass)
        assert gmsh_mass == pytest.approx(0.835 * mass, rel=0.01)
        # Simpson's 3/8 rule on the four sections' areas pi/4 chord thickness
        a = [math.pi / 4 * c * t for c, t in ((40, 10), (34, 8), (29, 6.5), (24, 5))]
        assert mass == pytest.approx(3 * 20 / 8 * (a[0] + 3 * a[1] + 3 * a[2] + a[3]), rel=0.01)
    else:  # fixed-order integration: 1e-5 (profile) to 5.7e-3 (extruded spline) off on B-splines
        assert gmsh_mass == pytest.approx(mass, rel=1e-2)


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("name", list(parts.PARTS))
def test_part_round_trip(written, name, fmt):
    """Re-read by gmsh (``meshing.import_cad``: IGES faces sewn, assemblies fragmented):
    same faces, same volume (area)."""
    part = parts.PARTS[name]
    path = written[name][fmt]
    assert path.stat().st_size > 0
    with parts.part_model(name):
        ref_faces, ref_mass = parts.measure(part.dim)
    with gmsh_session("reread"):
        try:
            tdim, tops = import_cad(path)
            faces, mass = parts.measure(tdim)
        except ValueError:
            tdim, faces, mass = None, None, None
    if fmt == "iges" and not part.iges_faces_solid and (tdim is None or faces != ref_faces):
        # documented limitation: faces-only IGES does not always give the solid(s) back (since
        # the faces left beside a sewn solid are removed, the revolved and seamed parts do)
        return
    assert tdim == part.dim
    assert faces == ref_faces
    # OpenCASCADE's faces-only IGES re-fits B-spline faces (the blade: 1.3e-4, the
    # extruded spline: 1e-5); its B-rep IGES prints them to fewer digits (blade: 1.5e-9)
    rel = {"iges": 5e-4, "iges_brep": 1e-8}.get(fmt, 1e-9)
    assert mass == pytest.approx(ref_mass, rel=rel)
    assert len(tops) == (2 if name == "assembly" else 1)


def test_write_part_leaves_gmsh_as_found(tmp_path):
    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("mine")
        gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        gmsh.model.occ.synchronize()
        parts.write_part("thin_wall", tmp_path, ("step",))
        assert gmsh.isInitialized()
        assert gmsh.model.getCurrent() == "mine"
        assert len(gmsh.model.getEntities(3)) == 1
    finally:
        gmsh.finalize()
    parts.write_part("thin_wall", tmp_path, ("brep",))
    assert not gmsh.isInitialized()
