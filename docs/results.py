"""Rerun the commands named on the results pages and write their output into the pages.

    python docs/results.py                 # every command (slow: well over an hour on 2 cores)
    python docs/results.py --only snap_loop --only transfer.py
    python docs/results.py --list          # the commands, by page
    python docs/results.py --only vs_ngspetsc --python vs_ngspetsc=/work/venvs/ngs/bin/python
    bash run.sh results [ARGS]             # the same

Each results page (``docs/pages/results/*.md``) ends with blocks of the form::

    <!-- results: python benchmarks/snap_loop.py -->
    ...
    <!-- /results -->

For each block whose command is selected, the command is run from the repository root
(``PYTHONPATH`` = the repository, ``OMP_NUM_THREADS=1``) and everything between the two
markers is replaced by its standard output, with the date, the wall time and the exit
status; a command that fails or times out is recorded as such (its last lines of standard
error included), and the page is written all the same.  Pages are rewritten block by block,
as each command finishes, so an interrupted run keeps what it measured.
"""

from __future__ import annotations

import argparse
import datetime
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PAGES = ROOT / "docs" / "pages" / "results"
BLOCK = re.compile(r"(<!-- results: (?P<cmd>.+?) -->\n)(?P<body>.*?)(<!-- /results -->)", re.S)


def blocks(page: Path) -> list[str]:
    """The commands of the result blocks of ``page``, in order."""
    return [m["cmd"] for m in BLOCK.finditer(page.read_text())]


#: OpenCASCADE's console messages (the readers and writers a benchmark calls itself print
#: coloured traces to standard output): dropped from what goes into the pages
OCC_TRACE = re.compile(r"\x1b\[32;1m.*?\x1b\[0m\n?", re.S)


def without_occ_traces(text: str) -> str:
    """``text`` without OpenCASCADE's coloured console messages.

    >>> without_occ_traces("a\\n\\x1b[32;1mTotal number of loaded entities 35.\\n\\x1b[0m\\nb\\n")
    'a\\nb\\n'
    """
    return OCC_TRACE.sub("", text)


def run(cmd: str, timeout: float, python: str = sys.executable) -> str:
    """Run ``cmd`` from the repository root with ``python`` for a leading ``python``; the
    Markdown that replaces its block's body."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    argv = shlex.split(cmd)
    if argv[0] == "python":
        argv[0] = python
    t0 = time.perf_counter()
    try:
        r = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
        out, status = without_occ_traces(r.stdout), f"exit status {r.returncode}"
        if r.returncode != 0:
            out += "\n[standard error, last lines]\n" + "\n".join(r.stderr.splitlines()[-20:])
    except subprocess.TimeoutExpired as e:
        partial = e.stdout.decode() if isinstance(e.stdout, bytes) else (e.stdout or "")
        out, status = without_occ_traces(partial), f"stopped after the time-out of {timeout:.0f} s"
    seconds = time.perf_counter() - t0
    when = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    fence = "````" if "```" in out else "```"
    return (f"{fence}text\n$ {cmd}\n{out.rstrip()}\n{fence}\n\n"
            f"*Run {when}, {seconds:.0f} s wall, {status}.*\n")


def update(page: Path, cmd: str, body: str) -> None:
    """Replace the body of the block of ``cmd`` on ``page``."""
    text = page.read_text()

    def replace(m: re.Match[str]) -> str:
        return m[1] + body + m[4] if m["cmd"] == cmd else m[0]

    page.write_text(BLOCK.sub(replace, text))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument("--only", action="append", default=[], metavar="TEXT",
                        help="run only the commands containing TEXT (repeatable)")
    parser.add_argument("--list", action="store_true", help="list the commands by page and exit")
    parser.add_argument("--timeout", type=float, default=7200.0, help="seconds per command")
    parser.add_argument("--python", action="append", default=[], metavar="TEXT=EXE",
                        help="run the commands containing TEXT with the interpreter EXE (repeatable;"
                             " e.g. a venv with ngsPETSc for vs_ngspetsc, see its docstring)")
    args = parser.parse_args(argv)
    pythons = [tuple(item.split("=", 1)) for item in args.python]
    if any(len(p) != 2 for p in pythons):
        parser.error("--python takes TEXT=EXE")
    pages = sorted(PAGES.glob("*.md"))
    todo = [(page, cmd) for page in pages for cmd in blocks(page)
            if not args.only or any(t in cmd for t in args.only)]
    if args.list:
        for page, cmd in todo:
            print(f"{page.relative_to(ROOT)}: {cmd}")
        return 0
    if not todo:
        print("no results block matches", file=sys.stderr)
        return 1
    for page, cmd in todo:
        print(f"{page.relative_to(ROOT)}: {cmd} ...", flush=True)
        python = next((exe for text, exe in pythons if text in cmd), sys.executable)
        body = run(cmd, args.timeout, python)
        update(page, cmd, body)
        print(f"  {body.rstrip().splitlines()[-1]}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
