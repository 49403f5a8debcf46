"""Every command line in README.md and docs/*.md, exactly as written: a documented command is a
promise.

The commands are read from the documents themselves (fenced ``bash`` blocks, and inline code that
starts with ``neoslam ``, ``make`` or ``pip``), in a fresh folder holding a tiny dataset at the
paths the documents name (``data/myrun``, ``data/irat_aus_28112011.bag``, ``runs/monday``...).
Each one is handled in one of five ways, and a command in no table fails the test, so a new
documented command must be classified here:

* ``RUN``: run for real, to the end, through the ``neoslam`` console script (shell redirections
  included); the exit code must be 0.
* ``VALIDATE``: commands whose work is set by a shipped config (the 2445-frame synthetic world, a
  30-second bench) or that wait for a robot. The exact argv goes through the real CLI; only the
  engine (``launch.run`` / ``throughput.run_bench``) is replaced by a check that builds the
  run's plan, binds the source parameters to the source's constructor (and, for file sources,
  opens the files), then stops. The engine itself is run by the other tests.
* synopsis lines (placeholders such as ``RUN_DIR``, ``[--flag ...]``, ``...``, ``a | b``): the
  command and every option they name must exist in that command's ``--help``.
* ``MAKE``: ``make -n TARGET`` in the repository (a test cannot run ``make test`` inside itself).
* ``ELSEWHERE``: not ours to run here, with the reason (another program, or a test that does).

The notes under ``studies/`` are a record of how the defaults were chosen, not a reference: the
commands they give (the studies' own runs, writing ``studies/results/``) are not read here.
"""

from __future__ import annotations

import inspect
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BIN = Path(sys.executable).parent

RUN = {
    "neoslam run --source folder -p path=data/myrun",
    "neoslam config list",
    "neoslam config show default > my.yaml",
    "neoslam map export runs/monday --out site.neoslam",
    "neoslam map info site.neoslam",
    "neoslam config show default",
    "neoslam config show irat2011",
    "neoslam config show my.yaml",
    "neoslam view runs/monday --save monday.rrd",
    "neoslam evaluate runs/monday --gt data/myrun/groundtruth.tum --gt-align-start",
}
VALIDATE = {
    "neoslam run",
    "neoslam run -p laps_cw=3 -p laps_ccw=2 -p seed=7",
    "neoslam run -c my.yaml",
    "neoslam run --view",
    "neoslam run --stages A,B --run-id field1 --connect tcp/10.0.0.5:7447",
    "neoslam run --stages rest --run-id field1 --connect tcp/10.0.0.5:7447",
    "neoslam run --stages rest --run-id field1 --router-listen tcp/0.0.0.0:7447",
    "neoslam run --stages A,B --run-id field1 --connect tcp/ROBOT:7447",
    "neoslam run -c irat2011 -p path=data/irat_aus_28112011.bag",
    "neoslam run -c irat2011 -p path=data/irat_aus_28112011.bag -p groundtruth_topic=null",
    "neoslam run --realtime --source zenoh-ros2 -p image_topic=/camera/image_raw "
    "-p odom_topic=/odom -p 'connect=[\"tcp/192.168.1.5:7447\"]'",
    "neoslam run --realtime --source zenoh-ros2 -p image_topic=/camera/image_raw -p odom_topic=/odom "
    "-p 'connect=[\"tcp/robot:7447\"]'",
    "neoslam bench emulate --tau 50,280,20,350 --rate 10 --duration 30 --topology both --out bench/results/emulate",
    "neoslam bench throughput --backbone random_alexnet --rates 10,13,20,30,35,40,45,60 --duration 30 --topology both "
    "--out bench/results/throughput",
    "neoslam bench throughput --backbone random_alexnet --rates 30 --duration 300 --topology pipeline --out bench/results/throughput",
    "neoslam bench throughput --rates 30,45,60 --duration 30 --topology both --out bench/results/throughput_default",
    "neoslam bench throughput --rates 60 --duration 300 --topology pipeline",
    "neoslam bench throughput --rates 60 --duration 300 --topology pipeline "
    "--out bench/results/throughput_default_60fps_5min/run1",
    "neoslam bench throughput --rates 60 --duration 300 --topology pipeline "
    "--out bench/results/throughput_default_60fps_5min/run2",
    "neoslam bench throughput --backbone random_alexnet --rates 30,45,60 --duration 30 --topology pipeline --projection sparse "
    "--out bench/results/throughput_sparse",
    "neoslam bench throughput --backbone random_alexnet --rates \"\" --scaling 20000 --out bench/results/throughput",
    "neoslam bench throughput --scaling 20000",
    "neoslam run -c paper",
    "neoslam run --oracle-templates",
    "neoslam run --oracle-templates --oracle-radius 0.25 --max-frames 1200",
    "neoslam run --oracle-templates --oracle-heading-tolerance 180",
    "neoslam compare --max-frames 300",
    "neoslam run --max-frames 200 --trace runs/trace.json",
    "neoslam run --realtime --source rmw-zenoh -p image_topic=/camera/image_raw -p odom_topic=/odom "
    "-p domain_id=0 -p 'connect=[\"tcp/robot:7447\"]'",
    "neoslam run --ros2-out rmw --ros2-connect tcp/localhost:7447",
    "neoslam run --ros2-out bridge --ros2-connect tcp/localhost:7447",
    "neoslam run --source camera -p device=0",
    "neoslam run --source camera -p url=rtsp://192.168.1.64:554/stream1",
    "neoslam run --source zenoh -p key=robot1/camera -p 'listen=[\"tcp/0.0.0.0:7450\"]'",
    "neoslam run --foxglove",
    "neoslam run --foxglove 0.0.0.0:8765",
}
MAKE = {"make run", "make test", "make bench", "make", 'make run ARGS="--max-frames 300"'}
ELSEWHERE = {
    "export": "a shell assignment (the split run's secret, docs/hosts.md); tests/test_parts.py sets it",
    "zenoh-bridge-ros2dds": "zenoh's bridge, run on the robot (not part of this package)",
    "ros2": "a ROS 2 installation's command (rmw_zenoh's router, foxglove_bridge), run on the ROS 2 side",
    "RMW_IMPLEMENTATION=rmw_zenoh_cpp": "RViz with rmw_zenoh, run on the ROS 2 side",
    "neoslam router": "a zenoh router that runs until Ctrl-C; tests/test_parts.py runs one on loopback",
    "neoslam camera": "reads a camera on the robot until Ctrl-C; tests/test_sources_camera.py runs it on an "
                      "MJPEG stream into a zenoh source, with the options the documents name",
    "pip install '.[view]'": "the Makefile's setup installs the [test] extra, which holds the viewer's rerun-sdk",
    "pip install 'neoslam-stream[foxglove]'": "the Makefile's setup installs the [test] extra, which holds foxglove-sdk",
    "neoslam view runs/monday --foxglove": "a server that runs until Ctrl-C; tests/test_foxglove.py serves a "
                                           "finished run the same way (with --duration)",
    "pip install .": "tests/test_packaging.py installs the wheel in a fresh venv and runs it",
    "pip install torch==2.13.0": "the Makefile's setup step, run by every `make run` / `make test`",
    "pip install evo": "evo, a GPL tool kept outside the package (its own environment); tests/test_evo.py runs it "
                       "where it is installed",
    "evo_ape": "evo's command, an outside tool; tests/test_evo.py runs it on our TUM files where evo is installed",
    "evo_rpe": "evo's command, an outside tool; tests/test_evo.py runs it on our TUM files where evo is installed",
    "python examples/publish_odometry.py": "the robot's side; tests/test_publish_odometry.py runs it against a run "
                                           "on loopback",
    ".venv/bin/python bench/camera_soak.py": "an hour of a live pipeline, measured on a quiet machine (its figures are "
                                             "the point); tests/test_camera_soak.py checks its computations and "
                                             "tests/test_sources_camera.py the camera it reads and the stream it serves",
}
PLACEHOLDER = re.compile(r"\b(RUN_DIR|OLD_RUN_DIR|DIR|FILE|MAP_FILE|CONFIG|NAME|KIND|HZ|N|S|X|FRAMES)\b")
FLAG = re.compile(r"(?<![\w-])(--?[A-Za-z][\w-]*)")


def _strip_comment(line: str) -> str:
    """The command without its trailing ``# comment`` (a # inside quotes is kept)."""
    out, quote = [], None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            break
        out.append(ch)
    return "".join(out).strip()


def documented_commands() -> list[tuple[str, str]]:
    """(document, command) for every command line in the documents, continuations joined."""
    found: list[tuple[str, str]] = []
    for doc in DOCS:
        text = doc.read_text()
        name = doc.relative_to(ROOT).as_posix()
        for block in re.finditer(r"```(?:bash|sh|console|shell)\n(.*?)```", text, re.S):
            pending = ""
            for raw in block.group(1).splitlines():
                line = pending + raw.strip()
                if line.endswith("\\"):
                    pending = line[:-1].rstrip() + " "
                    continue
                pending = ""
                cmd = _strip_comment(line)
                if cmd.startswith("[") and found and found[-1][0] == name:
                    # a synopsis wrapped without a backslash: its options continue the command
                    found[-1] = (name, f"{found[-1][1]} {' '.join(cmd.split())}")
                elif cmd:
                    found.append((name, " ".join(cmd.split())))
        prose = re.sub(r"```.*?```", "", text, flags=re.S)
        for span in re.finditer(r"`((?:neoslam|make|pip) [^`]*|make)`", prose):
            found.append((name, " ".join(span.group(1).split())))
    return found


def _is_synopsis(cmd: str) -> bool:
    """A usage line, or the bare name of a command (``neoslam bench throughput`` in prose)."""
    return bool("[" in cmd or "..." in cmd or " | " in cmd or PLACEHOLDER.search(cmd)
                or re.fullmatch(r"neoslam( [a-z]+)+", cmd))


def _classify(cmd: str) -> str:
    if cmd in RUN:
        return "run"
    if cmd in VALIDATE:
        return "validate"
    if cmd in MAKE:
        return "make"
    if any(cmd == k or cmd.startswith(k + " ") for k in ELSEWHERE):
        return "elsewhere"
    if cmd.startswith("neoslam") and _is_synopsis(cmd):
        return "synopsis"
    return "unclassified"


COMMANDS = sorted(set(documented_commands()))


def test_the_documents_hold_commands_and_every_one_is_classified():
    assert len(COMMANDS) > 20  # the extraction found the documents' commands
    unclassified = [(d, c) for d, c in COMMANDS if _classify(c) == "unclassified"]
    assert not unclassified, f"documented commands no test runs (add them to a table): {unclassified}"
    # no stale entries: every command of the tables is still documented
    documented = {c for _, c in COMMANDS}
    stale = sorted((RUN | VALIDATE | MAKE) - documented)
    assert not stale, f"commands the documents no longer hold: {stale}"


# ----------------------------------------------------------------------------- synopsis lines
def _help(words: list[str]) -> str:
    from neoslam_stream.cli import build_parser

    parser = build_parser()
    for w in words:  # walk the sub-commands: run, bench throughput, map export...
        sub = next((a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction"), None)
        if sub is None or w not in sub.choices:
            break
        parser = sub.choices[w]
    return parser.format_help()


@pytest.mark.parametrize("doc,cmd", [c for c in COMMANDS if _classify(c[1]) == "synopsis"],
                         ids=lambda v: v if "/" in v or v.endswith(".md") else None)
def test_synopsis_names_only_commands_and_options_that_exist(doc, cmd):
    for alt in cmd.split(" | "):  # "neoslam config list | neoslam config show NAME"
        words = shlex.split(alt.replace("[", " ").replace("]", " ").replace("|", " "))
        assert words[0] == "neoslam", f"{doc}: {alt}"
        sub = [w for w in words[1:] if re.fullmatch(r"[a-z]+", w)][:2]
        text = _help(sub)
        assert f"usage: neoslam {sub[0]}" in text, f"{doc}: `{alt}`: no command `neoslam {sub[0]}`"
        for flag in FLAG.findall(alt):
            assert re.search(rf"(?<![\w-]){re.escape(flag)}\b", text), \
                f"{doc}: `{alt}` names {flag}, which `neoslam {' '.join(sub)} --help` does not know"


# ----------------------------------------------------------------------------- make targets
@pytest.mark.parametrize("cmd", sorted(MAKE))
def test_make_targets_exist(cmd):
    r = subprocess.run(["make", "-n", *shlex.split(cmd)[1:]], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


# ----------------------------------------------------------------------------- the tiny dataset
def _write_irat_bag(path: Path) -> None:
    """A ROS 1 bag with the irat2011 config's topics: 6 JPEG frames, odometry and overhead pose."""
    import cv2
    import numpy as np
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    from neoslam_stream.config import load_config

    params = load_config("irat2011").source.params
    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types

    def header(t, i):
        return T["std_msgs/msg/Header"](seq=i, stamp=T["builtin_interfaces/msg/Time"](
            sec=int(t), nanosec=int(round((t % 1) * 1e9))), frame_id="base")

    vec, quat = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                       orientation=quat(x=0.0, y=0.0, z=0.0, w=1.0))
    rng = np.random.default_rng(0)
    msgs = []
    for i in range(20):
        t = 1.0 + 0.05 * i
        msgs.append((t, params["odom_topic"], "nav_msgs/msg/Odometry", T["nav_msgs/msg/Odometry"](
            header=header(t, i), child_frame_id="base",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](
                linear=vec(x=0.1, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.1)), covariance=np.zeros(36)))))
        msgs.append((t, params["groundtruth_topic"], "geometry_msgs/msg/PoseStamped",
                     T["geometry_msgs/msg/PoseStamped"](header=header(t, i), pose=pose)))
    for i in range(6):
        t = 1.01 + 0.15 * i
        jpeg = cv2.imencode(".jpg", rng.integers(0, 256, (120, 320, 3), dtype=np.uint8))[1]
        msgs.append((t, params["image_topic"], "sensor_msgs/msg/CompressedImage",
                     T["sensor_msgs/msg/CompressedImage"](header=header(t, i), format="jpeg",
                                                          data=np.asarray(jpeg, np.uint8).ravel())))
    with Writer(path) as w:
        conns = {topic: w.add_connection(topic, typ, typestore=ts)
                 for topic, typ in sorted({(m[1], m[2]) for m in msgs})}
        for t, topic, typ, m in sorted(msgs, key=lambda m: m[0]):
            w.write(conns[topic], int(round(t * 1e9)), ts.serialize_ros1(m, typ))


def _neoslam(args: str, cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    return subprocess.run(["bash", "-c", args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def datadir(tmp_path_factory) -> Path:
    """A fresh folder with the data the documents' commands name: a tiny image folder
    (``data/myrun``) and a bag with the irat2011 topics."""
    wd = tmp_path_factory.mktemp("docs")
    r = _neoslam("neoslam dataset synthetic --out data/myrun --frames 12 --width 160 --height 96", wd)
    assert r.returncode == 0, r.stderr
    _write_irat_bag(wd / "data" / "irat_aus_28112011.bag")
    return wd


@pytest.fixture(scope="module")
def workdir(datadir) -> Path:
    """... and a finished run with its state (``runs/monday``) for `neoslam map export`."""
    r = _neoslam("neoslam run --source folder -p path=data/myrun --out runs/monday --no-live", datadir)
    assert r.returncode == 0, r.stderr[-3000:]
    return datadir


@pytest.mark.slow
@pytest.mark.zenoh
@pytest.mark.parametrize("cmd", sorted(RUN, key=lambda c: ("map info" in c, "map export" in c, c)))
def test_documented_command_runs_as_written(cmd, workdir):
    if cmd == "neoslam config show my.yaml" and not (workdir / "my.yaml").exists():
        (workdir / "my.yaml").write_text("source: {kind: folder, params: {path: data/myrun}}\n")
    r = _neoslam(cmd, workdir)
    assert r.returncode == 0, f"`{cmd}` exited {r.returncode}:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    if cmd.startswith("neoslam run --source folder"):
        run_dir = max((workdir / "runs").iterdir(), key=lambda p: p.stat().st_mtime)
        rows = (run_dir / "trajectory.tum").read_text().splitlines()
        assert len([r for r in rows if r and not r.startswith("#")]) == 12  # every frame of data/myrun
    if "> my.yaml" in cmd:
        assert "source:" in (workdir / "my.yaml").read_text()


# ----------------------------------------------------------------------------- validated commands
class _Validated(Exception):
    pass


def _check_plan(cfg) -> None:
    from neoslam_stream.nodes.pipelines import build_plan
    from neoslam_stream.runtime.node import load_factory
    from neoslam_stream.sources import source_factory

    build_plan(cfg)
    factory = load_factory(source_factory(cfg.source.kind))
    inspect.signature(factory).bind(**cfg.source.params)  # TypeError on a parameter it does not take
    if cfg.source.kind in ("folder", "video", "bag"):  # open the files it names
        factory(**cfg.source.params).close()
    raise _Validated


@pytest.mark.parametrize("cmd", sorted(VALIDATE))
def test_documented_command_is_accepted_as_written(cmd, datadir, monkeypatch):
    import neoslam_stream.launch as launch
    import neoslam_stream.throughput as throughput
    from neoslam_stream.cli import main
    from neoslam_stream.config import load_config

    monkeypatch.chdir(datadir)
    if "-c my.yaml" in cmd and not (datadir / "my.yaml").exists():
        assert _neoslam("neoslam config show default > my.yaml", datadir).returncode == 0
    monkeypatch.setattr(launch, "run", lambda cfg, *a, **k: _check_plan(cfg))

    def bench(config, rates, duration, topologies, out, backbone, scaling, overrides, step):
        _check_plan(load_config(config, overrides))

    monkeypatch.setattr(throughput, "run_bench", bench)
    argv = shlex.split(cmd)
    assert argv[0] == "neoslam"
    with pytest.raises(_Validated):
        main(argv[1:])


def test_the_cli_example_in_help_is_documented():
    """`neoslam --help`'s examples are documented commands too: each is in a table above."""
    from neoslam_stream.cli import build_parser

    epilog = build_parser().epilog or ""
    examples = [_strip_comment(line) for line in epilog.splitlines() if line.strip().startswith("neoslam")]
    assert examples
    for ex in examples:
        assert _classify(" ".join(ex.split())) in ("run", "validate"), ex
