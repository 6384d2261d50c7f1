"""The corpus of CAD files written by other systems (meshes/corpus): every file is there, intact.

For every row of ``meshes/corpus/manifest.json``: the file exists, is at most 2 MB (the
corpus at most 40 MB in all), has the SHA-256 the manifest recorded, and OpenCASCADE reads
it with the face and solid counts recorded there, each face's surface kind (looking through
rectangular trims and offsets) as recorded. The manifest itself names, for every file, where
it came from and under which licence.
"""

from __future__ import annotations

import hashlib
import json
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
from corpus.inventory import cad_suffix, plain_file

CORPUS = Path(__file__).resolve().parent.parent / "meshes" / "corpus"
MANIFEST = json.loads((CORPUS / "manifest.json").read_text())
MAX_FILE = 2 * 1024 * 1024
MAX_TOTAL = 40 * 1024 * 1024
CAD_SUFFIXES = {".stp", ".step", ".igs", ".iges"}


def _kind(surface: Any) -> str:
    """``Geom_*`` class name without the prefix; trims and offsets show their basis."""
    from OCP.Geom import Geom_OffsetSurface, Geom_RectangularTrimmedSurface

    if isinstance(surface, Geom_RectangularTrimmedSurface):
        return f"Trimmed({_kind(surface.BasisSurface())})"
    if isinstance(surface, Geom_OffsetSurface):
        return f"Offset({_kind(surface.BasisSurface())})"
    return str(surface.DynamicType().Name()).removeprefix("Geom_")


def _read(path: Path) -> Any:
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.IGESControl import IGESControl_Reader
    from OCP.STEPControl import STEPControl_Reader

    step = cad_suffix(path) in {".stp", ".step"}
    reader = STEPControl_Reader() if step else IGESControl_Reader()
    assert reader.ReadFile(str(path)) == IFSelect_RetDone, f"OpenCASCADE cannot read {path.name}"
    reader.TransferRoots()
    return reader.OneShape()


def test_manifest_lists_every_file_once() -> None:
    on_disk = sorted(p.name for p in CORPUS.iterdir() if cad_suffix(p) in CAD_SUFFIXES)
    listed = [row["file"] for row in MANIFEST]
    assert sorted(listed) == on_disk
    assert len(set(listed)) == len(listed)
    for row in MANIFEST:
        assert row["repo"] and row["path"] and row["licence"], row["file"]


def test_sizes() -> None:
    sizes = {row["file"]: (CORPUS / row["file"]).stat().st_size for row in MANIFEST}
    too_big = {f: s for f, s in sizes.items() if s > MAX_FILE}
    assert not too_big
    assert sum(sizes.values()) <= MAX_TOTAL


#: files whose reading takes seconds (the 4 MB impeller): marked slow
SLOW_FILES = {"impeller_solidworks2010.igs.gz"}
ROWS = [
    pytest.param(row, id=row["file"], marks=[pytest.mark.slow] if row["file"] in SLOW_FILES else [])
    for row in MANIFEST
]


@pytest.mark.parametrize("row", ROWS)
def test_file_intact_and_read_as_recorded(row: dict[str, Any]) -> None:
    from OCP.BRep import BRep_Tool
    from OCP.TopAbs import TopAbs_FACE, TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    path = CORPUS / row["file"]
    data = path.read_bytes()
    assert len(data) == row["bytes"]
    assert hashlib.sha256(data).hexdigest() == row["sha256"]
    with plain_file(path) as plain:
        shape = _read(plain)
    assert not shape.IsNull()
    kinds: Counter[str] = Counter()
    explorer = TopExp_Explorer(shape, TopAbs_FACE)
    while explorer.More():
        kinds[_kind(BRep_Tool.Surface_s(TopoDS.Face(explorer.Current())))] += 1
        explorer.Next()
    assert sum(kinds.values()) == row["faces"]
    assert dict(kinds) == row["kinds"]
    solids = 0
    explorer = TopExp_Explorer(shape, TopAbs_SOLID)
    while explorer.More():
        solids += 1
        explorer.Next()
    assert solids == row["solids"]
