"""The README's in-process API example runs as written (in a scratch directory)."""

from __future__ import annotations

import os
import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs(tmp_path, capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    example = next(b for b in blocks if "NeoSLAM(" in b)
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        exec(compile(example, str(README), "exec"), {})
    finally:
        os.chdir(cwd)
    rows = (tmp_path / "out" / "templates.csv").read_text().splitlines()
    assert len(rows) == 1 + 300
    assert len((tmp_path / "out" / "trajectory.tum").read_text().splitlines()) == 300
    assert (tmp_path / "out" / "map.json").is_file()
