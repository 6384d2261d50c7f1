"""Inventory of the CAD corpus: what OpenCASCADE reads from each STEP/IGES file here.

Run ``python meshes/corpus/inventory.py [--json | --manifest] [files...]``. One row per file:
file name, originating system (from the STEP FILE_NAME or the IGES global section),
format/schema, face count, face counts by OpenCASCADE surface kind, solids, shells
and how many of the shells are closed.

``--manifest`` merges the rows with ``sources.json`` (where each file came from, its
licence and notes, written by hand) and writes ``manifest.json`` and ``MANIFEST.md``.

Surface kinds are the ``Geom_*`` class names without the prefix; a face on a
``Geom_RectangularTrimmedSurface`` is listed as ``Trimmed(<basis kind>)`` and a face
on a ``Geom_OffsetSurface`` as ``Offset(<basis kind>)``.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import re
import shutil
import sys
import tempfile
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
STEP_SUFFIXES = {".stp", ".step"}
IGES_SUFFIXES = {".igs", ".iges"}


def cad_suffix(path: Path) -> str:
    """The CAD extension of ``path`` (lower case), looking through a trailing ``.gz``."""
    suffixes = [s.lower() for s in path.suffixes]
    if suffixes and suffixes[-1] == ".gz":
        suffixes = suffixes[:-1]
    return suffixes[-1] if suffixes else ""


@contextmanager
def plain_file(path: Path) -> Iterator[Path]:
    """``path`` itself, or for ``x.igs.gz`` an uncompressed temporary copy ``x.igs``.

    Files above the corpus's 2 MB limit are kept gzip-compressed; OpenCASCADE and gmsh
    read only the plain file, so every consumer of the manifest opens files through this.
    """
    if not path.name.lower().endswith(".gz"):
        yield path
        return
    with tempfile.TemporaryDirectory() as tmp:
        plain = Path(tmp) / path.name[: -len(".gz")]
        with gzip.open(path, "rb") as src, plain.open("wb") as dst:
            shutil.copyfileobj(src, dst)
        yield plain


@dataclass
class Row:
    """What one file contains, as OpenCASCADE reads it."""

    file: str
    system: str
    format: str
    schema: str
    faces: int
    kinds: dict[str, int] = field(default_factory=dict)
    solids: int = 0
    shells: int = 0
    closed_shells: int = 0
    iges_entities: dict[int, int] = field(default_factory=dict)


def _step_strings(text: str, keyword: str) -> list[str]:
    """The quoted strings of the first ``keyword( ... );`` record of a STEP header."""
    match = re.search(keyword + r"\s*\((.*?)\)\s*;", text, re.S | re.I)
    if match is None:
        return []
    return re.findall(r"'((?:[^']|'')*)'", match.group(1))


def step_header(path: Path) -> tuple[str, str]:
    """(originating system, schema) from a STEP file's header section."""
    head = path.read_bytes()[:20000].decode(errors="replace")
    head = re.sub(r"/\*.*?\*/", "", head, flags=re.S)
    names = _step_strings(head, r"FILE_NAME")
    # FILE_NAME(name, time_stamp, (author), (organization), preprocessor_version,
    #           originating_system, authorization): strings 0, 1, then the lists.
    system = ""
    if len(names) >= 3:
        tail = names[-3:]
        preprocessor, originating = tail[0], tail[1]
        system = originating.strip() or preprocessor.strip()
        if preprocessor.strip() and preprocessor.strip() != system:
            system = f"{system} / {preprocessor.strip()}"
    schema = " ".join(_step_strings(head, r"FILE_SCHEMA"))
    return system, schema


def _hollerith_fields(text: str) -> list[str]:
    """Split an IGES global section into its fields (Hollerith strings kept whole)."""
    delim, end = ",", ";"
    if text.startswith("1H"):
        delim = text[2]
    fields: list[str] = []
    i, current = 0, ""
    while i < len(text):
        match = re.match(r"\s*(\d+)H", text[i:])
        if match and current.strip() == "":
            n = int(match.group(1))
            start = i + match.end()
            current = text[start : start + n]
            i = start + n
            continue
        ch = text[i]
        if ch in (delim, end):
            fields.append(current.strip())
            current = ""
            if ch == end and len(fields) > 2:
                break
        else:
            current += ch
        i += 1
    return fields


def iges_header(path: Path) -> tuple[str, str]:
    """(originating system, 'IGES <version>') from an IGES file's global section."""
    lines = path.read_text(errors="replace").splitlines()
    glob = "".join(line[:72] for line in lines if len(line) >= 73 and line[72] == "G")
    fields = _hollerith_fields(glob)
    # Global parameters: 3 file name, 4 native system id, 5 preprocessor version.
    system = ""
    if len(fields) > 5:
        system = fields[4] or fields[5]
        if fields[5] and fields[5] != fields[4]:
            system = f"{fields[4]} / {fields[5]}"
    version = ""
    if len(fields) > 22:
        version = fields[22]
    return system, f"IGES (version flag {version})" if version else "IGES"


def iges_entity_types(path: Path) -> dict[int, int]:
    """Entity type number -> count, from the directory entry section of an IGES file."""
    counts: Counter[int] = Counter()
    d_lines = [
        line for line in path.read_text(errors="replace").splitlines()
        if len(line) >= 73 and line[72] == "D"
    ]
    for line in d_lines[::2]:  # each entry is two lines; the type is in columns 1-8
        field_text = line[:8].strip()
        if field_text.isdigit():
            counts[int(field_text)] += 1
    return dict(sorted(counts.items()))


def surface_kind(surface: object) -> str:
    """The OpenCASCADE kind of a face's surface, looking through trims and offsets."""
    from OCP.Geom import Geom_OffsetSurface, Geom_RectangularTrimmedSurface

    name = surface.DynamicType().Name().removeprefix("Geom_")  # type: ignore[attr-defined]
    if isinstance(surface, Geom_RectangularTrimmedSurface):
        return f"Trimmed({surface_kind(surface.BasisSurface())})"
    if isinstance(surface, Geom_OffsetSurface):
        return f"Offset({surface_kind(surface.BasisSurface())})"
    return str(name)


def read_shape(path: Path) -> object:
    """Read a STEP or IGES file with OpenCASCADE; raises RuntimeError if nothing transfers."""
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.IGESControl import IGESControl_Reader
    from OCP.STEPControl import STEPControl_Reader

    reader = STEPControl_Reader() if cad_suffix(path) in STEP_SUFFIXES else IGESControl_Reader()
    if reader.ReadFile(str(path)) != IFSelect_RetDone:
        raise RuntimeError(f"{path.name}: OpenCASCADE could not read the file")
    reader.TransferRoots()
    shape = reader.OneShape()
    if shape.IsNull():
        raise RuntimeError(f"{path.name}: OpenCASCADE transferred no shape")
    return shape


def inventory(path: Path) -> Row:
    """Read ``path`` and count its faces by surface kind, its solids and shells."""
    from OCP.BRep import BRep_Tool
    from OCP.TopAbs import TopAbs_FACE, TopAbs_SHELL, TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    entities: dict[int, int] = {}
    with plain_file(path) as plain:
        if cad_suffix(plain) in STEP_SUFFIXES:
            system, schema = step_header(plain)
            fmt = "STEP"
        else:
            system, schema = iges_header(plain)
            fmt = "IGES"
            entities = iges_entity_types(plain)
        shape = read_shape(plain)
    kinds: Counter[str] = Counter()
    explorer = TopExp_Explorer(shape, TopAbs_FACE)
    while explorer.More():
        face = TopoDS.Face(explorer.Current())
        kinds[surface_kind(BRep_Tool.Surface_s(face))] += 1
        explorer.Next()
    solids = 0
    explorer = TopExp_Explorer(shape, TopAbs_SOLID)
    while explorer.More():
        solids += 1
        explorer.Next()
    shells = closed = 0
    explorer = TopExp_Explorer(shape, TopAbs_SHELL)
    while explorer.More():
        shells += 1
        closed += int(BRep_Tool.IsClosed_s(TopoDS.Shell(explorer.Current())))
        explorer.Next()
    return Row(
        file=path.name,
        system=system,
        format=fmt,
        schema=schema,
        faces=sum(kinds.values()),
        kinds=dict(sorted(kinds.items(), key=lambda kv: (-kv[1], kv[0]))),
        solids=solids,
        shells=shells,
        closed_shells=closed,
        iges_entities=entities,
    )


def corpus_files(folder: Path = HERE) -> list[Path]:
    """The STEP/IGES files of ``folder``, sorted by name."""
    suffixes = STEP_SUFFIXES | IGES_SUFFIXES
    return sorted(p for p in folder.iterdir() if cad_suffix(p) in suffixes)


def _quiet() -> None:
    """Keep OpenCASCADE's messages off the terminal."""
    from OCP.Message import Message, Message_Gravity

    for printer in Message.DefaultMessenger_s().Printers():
        printer.SetTraceLevel(Message_Gravity.Message_Fail)


def _kinds_text(kinds: dict[str, int]) -> str:
    return ", ".join(f"{k} {n}" for k, n in kinds.items())


def write_manifest(rows: list[Row], folder: Path = HERE) -> None:
    """Write ``manifest.json`` and ``MANIFEST.md`` from ``rows`` and ``sources.json``."""
    sources = {s["file"]: s for s in json.loads((folder / "sources.json").read_text())}
    missing = sorted({r.file for r in rows} - set(sources))
    if missing:
        raise SystemExit(f"no entry in sources.json for {missing}: add where they came from first")
    entries = []
    for r in rows:
        src = sources[r.file]
        notes = src["notes"]
        if r.shells and r.closed_shells < r.shells:
            notes += f"; {r.shells - r.closed_shells} of {r.shells} shells open"
        entries.append(
            {
                "file": r.file,
                "repo": src["repo"],
                "path": src["path"],
                "commit": src["commit"],
                "licence": src["licence"],
                "system": r.system,
                "format": r.format,
                "schema": r.schema,
                "faces": r.faces,
                "kinds": r.kinds,
                "solids": r.solids,
                "shells": r.shells,
                "closed_shells": r.closed_shells,
                "iges_entities": {str(k): n for k, n in r.iges_entities.items()},
                "bytes": (folder / r.file).stat().st_size,
                "sha256": hashlib.sha256((folder / r.file).read_bytes()).hexdigest(),
                "notes": notes,
            }
        )
    (folder / "manifest.json").write_text(json.dumps(entries, indent=1) + "\n")
    systems = sorted({e["system"] for e in entries})
    lines = [
        "# CAD corpus: STEP/IGES files written by other CAD systems",
        "",
        "Generated by `python meshes/corpus/inventory.py --manifest` from OpenCASCADE's reading of each",
        "file (faces by surface kind, solids, closed shells) and `sources.json` (origin, licence, notes).",
        "`Trimmed(X)` is a `Geom_RectangularTrimmedSurface` over X, `Offset(X)` a `Geom_OffsetSurface`.",
        "",
        f"{len(entries)} files, {sum(e['bytes'] for e in entries) / 1e6:.2f} MB, "
        f"{len(systems)} distinct originating-system strings.",
        "",
        "| file | source repository | path | commit | licence | originating system | format / schema "
        "| faces | surface kinds | solids | closed shells | notes |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for e in entries:
        commit = e["commit"][:12] if e["commit"] else "-"
        lines.append(
            f"| {e['file']} | {e['repo']} | {e['path']} | {commit} | {e['licence']} | {e['system']} "
            f"| {e['format']} {e['schema']} | {e['faces']} | {_kinds_text(e['kinds'])} | {e['solids']} "
            f"| {e['closed_shells']}/{e['shells']} | {e['notes']} |"
        )
    lines += ["", *coverage_lines(entries)]
    (folder / "MANIFEST.md").write_text("\n".join(lines) + "\n")


#: OpenCASCADE surface kinds the corpus should contain (plain, and under a rectangular trim)
WANTED_KINDS = [
    "Plane", "CylindricalSurface", "ConicalSurface", "SphericalSurface", "ToroidalSurface",
    "SurfaceOfRevolution", "SurfaceOfLinearExtrusion", "OffsetSurface", "BSplineSurface",
    "BezierSurface",
]
#: IGES entities the corpus should contain
WANTED_IGES = [128, 144, 143, 120, 122, 108, 140, 186, 514]
#: STEP application protocols, by a word of their schema name
WANTED_SCHEMAS = {"AP203": ("CONFIG_CONTROL", "CONFIGURATION_CONTROL"), "AP214": ("AUTOMOTIVE",),
                  "AP242": ("AP242",)}


def coverage_tags(entry: dict[str, Any]) -> set[str]:
    """What one manifest entry covers, as the row labels of the coverage table."""
    tags: set[str] = set()
    for name in entry["kinds"]:
        trimmed = name.startswith("Trimmed(")
        basis = name.removeprefix("Trimmed(").rstrip(")")
        basis = "OffsetSurface" if basis.startswith("Offset(") else basis
        tags.add(f"Trimmed({basis})" if trimmed else basis)
    tags |= {f"IGES {t}" for t in entry["iges_entities"]}
    if entry["format"] == "STEP":
        schema = entry["schema"].upper()
        tags |= {f"STEP {ap}" for ap, words in WANTED_SCHEMAS.items() if any(w in schema for w in words)}
    if entry["format"] == "IGES" and entry["faces"] > 0 and not {"186", "514"} & set(entry["iges_entities"]):
        tags.add("faces-only IGES (no 186/514)")
    if entry["solids"] > 1:
        tags.add("multi-solid")
    if 100 <= entry["faces"] <= 1000:
        tags.add("100-1000 faces")
    return tags


def coverage_lines(entries: list[dict[str, Any]]) -> list[str]:
    """The coverage section of MANIFEST.md: which files have which kind, entity, schema."""
    rows = [r for kind in WANTED_KINDS for r in (kind, f"Trimmed({kind})")]
    rows += [f"IGES {t}" for t in WANTED_IGES] + [f"STEP {ap}" for ap in WANTED_SCHEMAS]
    rows += ["faces-only IGES (no 186/514)", "multi-solid", "100-1000 faces"]
    tags = {e["file"]: coverage_tags(e) for e in entries}
    out = ["## Coverage", "", "| item | files |", "|---|---|"]
    for row in rows:
        hits = [f for f, t in tags.items() if row in t]
        out.append(f"| {row} | {', '.join(hits) if hits else '**none**'} |")
    return out


def main(argv: list[str]) -> int:
    as_json = "--json" in argv
    names = [a for a in argv if not a.startswith("--")]
    paths = [Path(n) for n in names] if names else corpus_files()
    _quiet()
    rows = [inventory(p) for p in paths]
    if "--manifest" in argv:
        write_manifest(rows)
        return 0
    if as_json:
        print(json.dumps([asdict(r) for r in rows], indent=1))
        return 0
    for r in rows:
        kinds = _kinds_text(r.kinds)
        print(
            f"{r.file} | {r.system} | {r.format} {r.schema} | {r.faces} | {kinds} | "
            f"solids {r.solids} | shells {r.closed_shells}/{r.shells} closed"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
