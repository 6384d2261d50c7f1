"""mkdocs hook (``hooks:`` in mkdocs.yml): files that are built, not written, join the site.

* ``api/``: the API reference, built by pdoc from the docstrings (``docs/build_api.py``);
  a pdoc warning fails the build, as in ``bash run.sh check``;
* ``flow_cd.png``, ``flow.json``, ``flow_demo_output.txt``: the flow demo's plot and data,
  kept in ``docs/`` (the README shows the plot from there).

Pages link them by their site paths (``api/nagata_snap.html``, ``flow_cd.png``), which
mkdocs then checks like any other link.
"""

from __future__ import annotations

import importlib.util
import shutil
import tempfile
from pathlib import Path

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File, Files

DOCS = Path(__file__).resolve().parent
DEMO_OUTPUT = ("flow_cd.png", "flow.json", "flow_demo_output.txt")
_tmp: list[Path] = []


def _build_api(output: Path) -> list[str]:
    spec = importlib.util.spec_from_file_location("build_api", DOCS / "build_api.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.build(output)


def on_files(files: Files, config: MkDocsConfig) -> Files:
    api = Path(tempfile.mkdtemp(prefix="nagata_snap_api_"))
    _tmp.append(api)
    problems = _build_api(api)
    if problems:
        raise PluginError("API reference: pdoc warned:\n" + "\n".join(problems))
    for path in sorted(p for p in api.rglob("*") if p.is_file()):
        files.append(File.generated(config, "api/" + path.relative_to(api).as_posix(), abs_src_path=str(path)))
    for name in DEMO_OUTPUT:
        files.append(File.generated(config, name, abs_src_path=str(DOCS / name)))
    return files


def on_post_build(config: MkDocsConfig) -> None:
    while _tmp:
        shutil.rmtree(_tmp.pop(), ignore_errors=True)
