"""Check the README's shape and the design page's package map against the tree.

    python docs/layout.py        # exit status 1 and the problems if any

* ``docs/pages/design.md``, section "Package map": a code block that draws the
  tree by indentation (two spaces a level): ``nagata_snap/`` at the left
  margin, its subpackages (``mesh/``) and modules (``snapper.py``) below it,
  each followed by its description; it must name every module of the package
  and only those (package ``__init__.py`` files are not listed);
* ``README.md``: at most ``README_MAX_LINES`` lines, and every relative link
  in it points at a file of the repository.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

PACKAGE = "nagata_snap"
ROOT = Path(__file__).resolve().parent.parent
MAP_PAGE = ROOT / "docs" / "pages" / "design.md"
MAP_SECTION = "Package map"
README_MAX_LINES = 250

_ENTRY = re.compile(r"^(?P<indent> *)(?P<name>[\w.]+/|[\w.]+\.py)(\s|$)")


def listed(page: str, package: str = PACKAGE) -> set[str]:
    """Paths (``nagata_snap/mesh/boundary.py``) of the modules the package map of ``page`` draws."""
    section = page.split(f"\n## {MAP_SECTION}", 1)[1].split("\n## ", 1)[0]
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


def readme_problems(readme: str) -> list[str]:
    """What is wrong with the README's shape: its length and its relative links."""
    problems = []
    n = len(readme.splitlines())
    if n > README_MAX_LINES:
        problems.append(f"README.md has {n} lines, at most {README_MAX_LINES}: move details to docs/pages")
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", readme):
        if "://" not in target and not (ROOT / target).exists():
            problems.append(f"README.md links to {target}, which does not exist")
    return problems


def main() -> int:
    drawn = listed(MAP_PAGE.read_text())
    tree = modules()
    where = f"{MAP_PAGE.relative_to(ROOT)} {MAP_SECTION}"
    for path in sorted(tree - drawn):
        print(f"{where}: {path} is missing", file=sys.stderr)
    for path in sorted(drawn - tree):
        print(f"{where}: {path} is not in the tree", file=sys.stderr)
    problems = readme_problems((ROOT / "README.md").read_text())
    for problem in problems:
        print(problem, file=sys.stderr)
    if tree != drawn or problems:
        return 1
    print(f"{where}: the {len(tree)} modules of {PACKAGE}/ as in the tree; README.md: "
          f"{len((ROOT / 'README.md').read_text().splitlines())} lines, its links resolve")
    return 0


if __name__ == "__main__":
    sys.exit(main())
