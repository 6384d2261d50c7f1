"""Check that the README's "Layout" section names every module of the package, and only those.

    python docs/layout.py        # exit status 1 and the differences if they disagree

The section is a code block that draws the tree by indentation (two spaces
a level): ``nagata_snap/`` at the left margin, its subpackages (``mesh/``)
and modules (``snapper.py``) below it, each followed by its description.
Package ``__init__.py`` files are not listed there.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

PACKAGE = "nagata_snap"
ROOT = Path(__file__).resolve().parent.parent

_ENTRY = re.compile(r"^(?P<indent> *)(?P<name>[\w.]+/|[\w.]+\.py)(\s|$)")


def listed(readme: str, package: str = PACKAGE) -> set[str]:
    """Paths (``nagata_snap/mesh/boundary.py``) of the modules the Layout section draws."""
    section = readme.split("\n## Layout", 1)[1].split("\n## ", 1)[0]
    block = section.split("```", 2)[1]
    paths: set[str] = set()
    stack: list[tuple[int, str]] = []  # (indent, folder) of the enclosing folders
    for line in block.splitlines():
        m = _ENTRY.match(line)
        if m is None:
            continue  # a description continued on the next line
        indent, name = len(m["indent"]), m["name"]
        while stack and stack[-1][0] >= indent:
            stack.pop()
        if not stack and name != f"{package}/":
            continue  # meshes/, tests/, ...: outside the package
        path = "/".join([*(folder for _, folder in stack), name.rstrip("/")])
        if name.endswith("/"):
            stack.append((indent, name.rstrip("/")))
        else:
            paths.add(path)
    return paths


def modules(package: str = PACKAGE) -> set[str]:
    """Paths of the package's modules in the tree (without ``__init__.py``)."""
    return {p.relative_to(ROOT).as_posix() for p in (ROOT / package).rglob("*.py")
            if p.name != "__init__.py"}


def main() -> int:
    drawn = listed((ROOT / "README.md").read_text())
    tree = modules()
    for path in sorted(tree - drawn):
        print(f"README Layout: {path} is missing", file=sys.stderr)
    for path in sorted(drawn - tree):
        print(f"README Layout: {path} is not in the tree", file=sys.stderr)
    if tree != drawn:
        return 1
    print(f"README Layout: the {len(tree)} modules of {PACKAGE}/ as in the tree")
    return 0


if __name__ == "__main__":
    sys.exit(main())
