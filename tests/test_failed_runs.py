"""A run that fails says so: report.json's ``status`` and ``failure``, the source's failure counted,
no rate or prediction measured over nothing, no empty output files that look like results, and
one line from the command line."""

import json
import subprocess
import sys

import pytest
import yaml

from neoslam_stream.config import load_config
from neoslam_stream.runtime.collector import FinalTracker
from neoslam_stream.runtime.report import build_report, mark_status

RESULT_FILES = ("trajectory.tum", "templates.csv", "closures.csv", "map.json", "trajectory_map.tum",
                "outputs.mcap", "groundtruth.tum", "odometry.tum")


@pytest.mark.zenoh
def test_a_run_whose_source_fails_reports_a_failed_run_and_exits_with_one_line(tmp_path):
    bag = tmp_path / "robot.bag"
    bag.write_bytes(b"\x93 these bytes are no bag \x00" * 500)
    cfg = {"run": {"pipeline": "ratslam", "topology": "monolithic", "mode": "lossless", "live": False},
           "source": {"kind": "bag", "params": {"path": str(bag), "image_topic": "/cam"}}}
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    run_dir = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "neoslam_stream.cli", "run", "-c", str(tmp_path / "cfg.yaml"),
                           "--out", str(run_dir)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in proc.stderr
    assert errors[0].startswith("error: the source failed:") and "not a ROS 1 bag" in errors[0]
    assert str(run_dir / "report.json") in errors[0]
    rep = json.loads((run_dir / "report.json").read_text())
    assert rep["status"] == "failed" and "not a ROS 1 bag" in rep["failure"]
    assert rep["source_errors"] == 1 and rep["errors"] >= 1
    (cause,) = rep["source_error_causes"]
    assert "not a ROS 1 bag" in cause
    assert rep["frames_in"] == 0 and rep["frames_out"] == 0
    for key in ("f_pipeline_predicted", "predicted_loss", "f_in", "f_out", "loss", "bottleneck"):
        assert rep[key] is None, key
    left = [name for name in RESULT_FILES if (run_dir / name).exists()]
    assert left == [], f"a failed run left {left}"


@pytest.mark.zenoh
def test_a_stage_that_refuses_its_state_makes_a_failed_report(tmp_path, monkeypatch):
    """The supervisor's real start-up, with processes that only pretend: the monitor comes up, every
    worker exits with EXIT_STATE_REFUSED (a checkpoint made with other parameters)."""
    from neoslam_stream.nodes.pipelines import build_plan
    from neoslam_stream.runtime.topology import RunError, Supervisor
    from neoslam_stream.runtime.worker import EXIT_STATE_REFUSED

    cfg = load_config("default")
    sup = Supervisor(cfg, build_plan(cfg), tmp_path / "run", source_factory="neoslam_stream.sources:SOURCES")

    class Pretend:
        def __init__(self, exitcode):
            self.exitcode = exitcode

        def is_alive(self):
            return self.exitcode is None

        def join(self, timeout=None):
            if self.exitcode is None:
                self.exitcode = 0  # the stop command was obeyed

        terminate = kill = join

    def start(name, target, spec):
        sup.children.procs[name] = Pretend(None if name == "monitor" else EXIT_STATE_REFUSED)

    monkeypatch.setattr(sup.children, "start", start)
    monkeypatch.setattr(sup.children, "alive_tokens", lambda: {"monitor"})
    with pytest.raises(RunError, match="refused the saved state") as err:
        sup.run()
    assert str(tmp_path / "run" / "report.json") in str(err.value)
    rep = json.loads((tmp_path / "run" / "report.json").read_text())
    assert rep["status"] == "failed" and "refused the saved state" in rep["failure"]
    assert rep["source_failure"] is None and rep["source_errors"] == 0  # not the source's doing
    assert rep["f_pipeline_predicted"] is None and rep["f_in"] is None and rep["loss"] is None


def _stage(processed, tau):
    return {"stage": "A", "pid": 1, "received": processed, "processed": processed, "tau_mean_ms": tau,
            "tau_p50_ms": tau, "tau_p95_ms": tau, "time": 10.0, "started": 0.0, "inputs": {}}


def test_no_prediction_from_stages_that_processed_nothing():
    src = {"frames_in": 0, "published_ranges": [], "errors": 0}
    rep = build_report({"source": src, "A": _stage(0, 0.0055)}, FinalTracker(), {"A": ["A"]}, {})
    assert rep["f_pipeline_predicted"] is None and rep["bottleneck"] is None
    rep = build_report({"source": src, "A": _stage(5, 20.0)}, FinalTracker(), {"A": ["A"]}, {})
    assert rep["f_pipeline_predicted"] == pytest.approx(50.0)  # 1 / 20 ms, when measured


def test_mark_status():
    rep = build_report({}, FinalTracker(), {"A": ["A"]}, {"rate": 10.0})
    assert rep["f_in"] == 10.0  # the configured rate stands in for a measured one
    mark_status(rep, "the source failed: X", False, "X")
    assert (rep["status"], rep["failure"], rep["source_errors"], rep["errors"]) == ("failed", "the source failed: X", 1, 1)
    assert rep["source_error_causes"] == {"X": 1} and rep["f_in"] is None
    done = build_report({}, FinalTracker(), {"A": ["A"]}, {"rate": 10.0})
    assert mark_status(done, None, False)["status"] == "completed" and done["f_in"] == 10.0
    assert mark_status(done, None, True)["status"] == "interrupted"


def test_a_recorder_that_recorded_nothing_leaves_no_output_files(tmp_path):
    from neoslam_stream.nodes.recorder import RecorderNode

    run = tmp_path / "run"
    run.mkdir()
    (run / "trajectory.tum").write_text("0.0 1 2 0 0 0 0 1\n")  # an earlier run's, in this folder
    (run / "map.json").write_text('{"nodes": [{"id": 0}], "links": []}')
    rec = RecorderNode()
    rec.run_dir, rec.run_id = str(run), "r-failed"
    rec.folder.on_map({"nodes": [], "links": []})  # the experience map's final (empty) map
    rec.flush()
    rec.close()
    assert [p.name for p in run.iterdir()] == []


def test_the_summary_of_a_failed_run_and_of_a_run_without_ground_truth(capsys):
    from neoslam_stream.cli import print_summary

    rep = build_report({}, FinalTracker(), {"A": ["A"]}, {"run": "x"})
    mark_status(rep, "the source failed: ValueError: cannot read bag b.bag", False, "ValueError: cannot read bag b.bag")
    print_summary(rep)
    out = " ".join(capsys.readouterr().out.split())  # rich wraps long lines
    assert "the run FAILED: the source failed: ValueError: cannot read bag b.bag" in out
    assert "f_in n/a" in out and "f_pipeline n/a" in out
    note = "ground-truth topic '/overhead/pose' is not in b.bag: running without ground truth"
    ok = build_report({"source": {"frames_in": 0, "info": {"warnings": [note]}}}, FinalTracker(), {"A": ["A"]}, {})
    print_summary(mark_status(ok, None, False))
    out = " ".join(capsys.readouterr().out.split())
    assert f"source: {note}" in out and "FAILED" not in out
