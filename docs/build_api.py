"""Build the API reference of ``nagata_snap`` from its docstrings with pdoc; fail on any warning.

    python docs/build_api.py OUTPUT_DIR      # (bash run.sh docs [OUTPUT_DIR])

Every module of the package gets a page (a package's ``__all__`` lists only
its public names, so the modules are named explicitly).  Docstrings are
Google style with Sphinx roles (``:class:`Snapper```), which pdoc's
``google`` docformat renders.  Exit status 1 if pdoc warned (an annotation it
cannot resolve, a module it cannot import, ...): each warning is printed.

One pdoc limitation is not counted: it cannot resolve postponed annotations of
the ``__init__`` that ``typing.NamedTuple`` generates (pdoc issue 765); such a
warning is dropped only for a NamedTuple whose annotations
``typing.get_type_hints`` resolves, so a wrong annotation still fails.
"""

from __future__ import annotations

import importlib
import re
import sys
import typing
import warnings
from pathlib import Path

import pdoc
import pdoc.extract
import pdoc.render

PACKAGE = "nagata_snap"
ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # document this checkout, whichever copy is installed

_NAMEDTUPLE_INIT = re.compile(r"Error parsing type annotation .* for (?P<name>[\w.]+)\.__init__\. ")


def modules(package: str = PACKAGE) -> list[str]:
    """Every module of ``package`` (from its files), each once in pdoc's walk.

    pdoc walks a package into the submodules its ``__all__`` names (e.g.
    ``smoothing.smooth``, also a function there); those are not named again.
    """
    names = []
    for path in sorted((ROOT / package).rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    walked = {m for n in names for m in pdoc.extract.walk_specs([n]) if m != n}
    return [n for n in names if n not in walked]


def _resolve(fullname: str) -> object:
    """The object named ``fullname`` (``package.module.Class``), or None."""
    parts = fullname.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:k]))
        except ImportError:
            continue
        for attr in parts[k:]:
            obj = getattr(obj, attr, None)
        return obj
    return None


def _known_limitation(message: str) -> bool:
    """True for pdoc's NamedTuple ``__init__`` warning on a NamedTuple whose hints resolve."""
    m = _NAMEDTUPLE_INIT.match(message)
    if m is None:
        return False
    cls = _resolve(m["name"])
    if not (isinstance(cls, type) and issubclass(cls, tuple) and hasattr(cls, "_fields")):
        return False
    typing.get_type_hints(cls)  # raises (and fails the build) if an annotation is wrong
    return True


def build(output: Path) -> list[str]:
    """Write the HTML reference into ``output``; return pdoc's warnings."""
    pdoc.render.configure(docformat="google")
    with warnings.catch_warnings(record=True) as caught:
        pdoc.pdoc(*modules(), output_directory=output)
    messages = [str(w.message) for w in caught]
    return [m for m in messages if not _known_limitation(m)]


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python docs/build_api.py OUTPUT_DIR", file=sys.stderr)
        return 2
    output = Path(argv[0])
    problems = build(output)
    for m in problems:
        print(f"pdoc warning: {m}", file=sys.stderr)
    if problems:
        print(f"API reference: {len(problems)} pdoc warnings (fix the docstrings or annotations)",
              file=sys.stderr)
        return 1
    print(f"API reference: {len(list(output.rglob('*.html')))} pages in {output}, no warnings")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
