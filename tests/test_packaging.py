"""`pip install .` into a fresh virtual environment, then `neoslam run` from another directory:
the package must not depend on the repository's layout (configs are package data, no top-level
`stages`). Nothing is downloaded: the wheel is built without build isolation and installed
without dependencies; the fresh environment borrows the test environment's dependencies
through a .pth file (which does not bring the editable install of the repository along)."""

from __future__ import annotations

import json
import os
import site
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                    "-q", "-w", str(out), str(ROOT)], check=True, timeout=300,
                   cwd=tmp_path_factory.mktemp("build_cwd"))
    (whl,) = out.glob("neoslam_stream-*.whl")
    return whl


def test_wheel_holds_one_namespace_and_its_configs(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert tops == {"neoslam_stream"}
    for cfg in ("default", "irat2011", "stlucia", "robotarium", "fiu_lake", "emulate"):
        assert f"neoslam_stream/configs/{cfg}.yaml" in names
    assert "neoslam_stream/algorithms/spatial_view.py" in names and "neoslam_stream/nodes/recorder.py" in names
    assert "neoslam_stream/viewer/foxglove_layout.json" in names  # the Foxglove layout (docs/foxglove.md)


def test_fresh_venv_runs_from_any_directory(wheel, tmp_path):
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True, clear=True).create(env_dir)
    py = env_dir / "bin" / "python"
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    # the test environment's site-packages, for torch, zenoh, numpy...: a plain path in a .pth file
    deps = [p for p in site.getsitepackages() if Path(p).is_dir()]
    Path(purelib, "borrowed_deps.pth").write_text("\n".join(deps) + "\n")
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)],
                   check=True, timeout=300)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    where = subprocess.run([str(py), "-c", "import neoslam_stream, sys; print(neoslam_stream.__file__)"],
                           capture_output=True, text=True, check=True, cwd=elsewhere, env=env).stdout
    assert where.startswith(purelib) and str(ROOT) not in where  # the installed copy, not the clone
    neoslam = env_dir / "bin" / "neoslam"
    listed = subprocess.run([str(neoslam), "config", "list"], capture_output=True, text=True, check=True,
                            cwd=elsewhere, env=env).stdout.split()
    assert "default" in listed and "irat2011" in listed
    res = subprocess.run([str(neoslam), "run", "--max-frames", "30", "--out", "out", "--no-live"],
                         capture_output=True, text=True, cwd=elsewhere, env=env, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    report = json.loads((elsewhere / "out" / "report.json").read_text())
    assert report["frames_out"] == 30 and report["errors"] == 0
    assert len((elsewhere / "out" / "trajectory.tum").read_text().splitlines()) == 30
