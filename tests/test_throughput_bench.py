"""``neoslam bench throughput``: the table/summary helpers on hand-made reports, and a smoke run.

No timing is asserted: the bench measures speed, the tests only check that it runs and that its
bookkeeping (loss, sustainable rate, table, scaling samples) follows the definitions.
"""

from __future__ import annotations

import json

from neoslam_stream.cli import main
from neoslam_stream.throughput import _fit_rss, _scaling_rows, paper_table, summarise, sustainable


def _report(frames_in, frames_out, loss):
    stage = {"worker": "w_A", "tau_p50_ms": 5.0, "tau_p95_ms": 7.0, "tau_mean_ms": 5.5, "processed": frames_out,
             "dropped": frames_in - frames_out, "errors": 0, "cpu_mean_percent": 20.0, "rss_mb": 300.0,
             "info": {"backbone": "random_alexnet", "backbone_is_random": True}}
    return {"frames_in": frames_in, "frames_out": frames_out, "loss": loss, "f_in": 10.0, "f_out": 9.0,
            "stages": {"A": stage}, "bottleneck": "A", "bottleneck_tau_ms": 5.5, "f_pipeline_predicted": 181.8,
            "predicted_loss": 0.0, "latency_p50_ms": 40.0, "latency_p95_ms": 60.0, "errors": 0}


def test_summary_has_the_issue_keys_and_the_table_the_papers_form():
    rows = [summarise(_report(100, 100, 0.0), "pipeline", 10.0, 10.0),
            summarise(_report(130, 13, 0.9), "monolithic", 13.0, 10.0)]
    for key in ("topology", "rate", "duration_s", "frames_in", "frames_processed", "loss", "stages",
                "bottleneck", "f_pipeline_predicted", "latency_p50_ms", "latency_p95_ms"):
        assert key in rows[0]
    assert rows[0]["stages"]["A"]["cpu_percent"] == 20.0 and rows[0]["backbone_is_random"] is True
    table = paper_table(rows).splitlines()
    assert [c.strip() for c in table[0].strip("|").split("|")] == ["Algorithm", "Processed Frames", "Data Loss"]
    assert "13 of 130" in table[2] and "90.0 %" in table[2]  # monolithic sorts first
    assert "100 of 100" in table[3] and "0.0 %" in table[3]


def test_sustainable_rate_stops_at_the_first_lossy_rate_and_prefers_the_longest_run():
    def row(rate, loss, duration=60.0):
        return {"topology": "pipeline", "rate": rate, "loss": loss, "duration_s": duration}

    runs = [row(10, 0.0), row(20, 0.0005), row(30, 0.01), row(45, 0.0)]
    assert sustainable(runs, "pipeline") == 20  # 45 is not counted: 30 already lost frames
    runs.append(row(30, 0.0, duration=300.0))  # a longer run at 30 FPS without loss overrides
    assert sustainable(runs, "pipeline") == 45
    assert sustainable(runs, "monolithic") is None


def test_scaling_rows_sample_every_step_and_fit_rss(tmp_path):
    lines = []
    for i, done in enumerate([0, 400, 1000, 1500, 2100, 2900, 3000]):
        lines.append(json.dumps({"t_s": float(i), "frames_in": done, "stages": {
            "C": {"worker": "w_C", "rss_mb": 100.0 + done / 10, "info": {"segments": done, "synapses": 2 * done}},
            "D": {"worker": "w_D", "rss_mb": 50.0, "tau_recent_p50_ms": 0.1, "info": {"intervals": done // 2}},
            "experience_map": {"worker": "w_D", "processed": done, "rss_mb": 50.0,
                               "info": {"experiences": done // 10, "links": done // 9, "relax_ms_last": 1.0}}}}))
    (tmp_path / "stats.jsonl").write_text("\n".join(lines) + "\nnot json\n")
    rows = _scaling_rows(tmp_path / "stats.jsonl", 1000)
    assert [r["frames"] for r in rows] == [1000, 2100, 3000]  # first snapshot past each multiple
    assert rows[0]["tm_segments"] == 1000 and rows[0]["svc_intervals"] == 500 and rows[0]["em_links"] == 111
    assert rows[0]["rss_total_mb"] == 100.0 + 100.0 + 50.0  # D and the experience map share w_D
    # RSS = 150 + f/10 exactly: the fit through the second half extrapolates the same line
    assert abs(_fit_rss(rows, 100_000) - (150.0 + 10_000.0)) < 1e-6


def test_smoke_run_writes_throughput_json(tmp_path, capsys):
    out = tmp_path / "bench"
    rc = main(["bench", "throughput", "--rates", "6", "--duration", "4", "--topology", "pipeline",
               "--projection", "sparse", "--scaling", "150", "--scaling-step", "50", "--out", str(out)])
    assert rc == 0
    res = json.loads((out / "throughput.json").read_text())
    (r,) = res["runs"]
    assert r["topology"] == "pipeline" and r["rate"] == 6.0
    assert r["frames_in"] > 0 and 0 <= r["frames_processed"] <= r["frames_in"]
    assert 0.0 <= r["loss"] <= 1.0
    assert {"A", "B", "C", "D", "pose_cells", "experience_map"} <= set(r["stages"])
    # no --backbone: the shipped default's backbone, as `neoslam run` resolves it (not the random one)
    from neoslam_stream.algorithms.features import resolve_backbone
    from neoslam_stream.config import load_config

    assert r["backbone"] == resolve_backbone(load_config("default").features) != "random_alexnet"
    assert r["backbone_is_random"] is False
    assert r["host"]["steal_s"] >= 0  # each row says what the hypervisor took over its run
    assert "Processed Frames" in res["paper_table"]
    sc = res["scaling"]
    assert sc["frames"] == 150 and sc["loss"] == 0.0  # lossless
    assert (out / "throughput.png").stat().st_size > 0
    assert "Processed Frames" in capsys.readouterr().out


def test_report_memory_counts_each_worker_once_and_sums_pss():
    from neoslam_stream.runtime.monitor import FinalTracker, build_report

    def st(pss, rss):
        return {"time": 10.0, "started": 0.0, "pss_mb": pss, "rss_mb": rss, "inputs": {}}

    # the recorder shares the experience map's process: its figures are that process's, counted once
    stats = {"source": {"frames_in": 0}, "A": st(300.0, 500.0), "experience_map": st(80.0, 200.0),
             "recorder": st(80.0, 200.0)}
    workers = {"A": ["A"], "experience_map": ["experience_map", "recorder"]}
    mem = build_report(stats, FinalTracker(), workers, {})["memory"]
    assert mem == {"rss_total_mb": 700.0, "pss_total_mb": 380.0, "workers": 2}
    stats["A"]["pss_mb"] = None  # a platform without PSS: no made-up total
    assert build_report(stats, FinalTracker(), workers, {})["memory"]["pss_total_mb"] is None
