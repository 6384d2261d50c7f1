"""The README's Python examples run as written (from the repository root)."""

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_readme_examples_run(tmp_path):
    text = Path(ROOT, "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert blocks, "README has no python example"
    for i, code in enumerate(blocks):
        script = tmp_path / f"example{i}.py"
        script.write_text(f"import sys\nsys.path.insert(0, {ROOT!r})\n" + code)
        r = subprocess.run([sys.executable, str(script)], cwd=ROOT, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, f"README example {i} failed:\n{r.stdout}\n{r.stderr}"
        if "max distance from the circle" in code:
            d = float(r.stdout.strip().splitlines()[-1].split(":")[-1])
            assert d < 1e-4
