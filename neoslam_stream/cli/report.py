"""What the commands print: a run's summary table, its evaluation and the comparison table."""

from __future__ import annotations

import sys
from typing import Any


def platform_lines(cfg: Any) -> list[str]:
    """What a run says at its start about the robot it assumes (``platform:``): its quantities, and,
    when they are the synthetic world's robot's while the source is another, the one line to set
    the real robot's."""
    from ..config import load_config

    p = cfg.platform
    lines = [f"platform: typical speed {p.speed_mps:g} m/s, shortest loop {p.shortest_loop_m:g} m, "
             f"area {p.area_m:g} m"]
    if cfg.source.kind != "synthetic" and p == load_config("default").platform:
        lines.append("  (the synthetic world's robot, the default's: set your robot's in your config, "
                     "e.g. platform: {speed_mps: 0.5, shortest_loop_m: 40, area_m: 30})")
    return lines


def _table(title: str, caption: str | None = None) -> Any:
    """A compact table (no vertical rules, one space between columns): 80 columns show whole names
    and every value (tests/test_tables.py)."""
    from rich import box
    from rich.table import Table

    return Table(title=title, caption=caption, box=box.SIMPLE_HEAD, pad_edge=False, padding=(0, 1, 0, 0),
                 caption_justify="left", title_justify="left", min_width=len(title))


def summary_table(report: dict[str, Any]) -> Any:
    """report.json's stages as a table, a row per stage."""
    from ..runtime.monitor import figure

    stages = report.get("stages", {})
    t = _table(f"run {report.get('run')} ({report.get('topology')}, {report.get('mode')})",
               "tau: service time per message (ms); dropped: evicted from its queue or lost on the way; "
               "errors: inputs refused")
    t.add_column("stage", no_wrap=True, min_width=max([5, *map(len, stages)]))
    for col in ("processed", "tau p50", "tau p95", "dropped", "errors"):
        t.add_column(col, justify="right", no_wrap=True)
    for name, st in stages.items():
        if st.get("missing"):
            t.add_row(name, "missing", "", "", "", "")
            continue
        t.add_row(name, str(st["processed"]), figure(st["tau_p50_ms"]), figure(st["tau_p95_ms"]),
                  str(st["dropped"]), str(st["errors"]))
    return t


def print_summary(report: dict[str, Any]) -> None:
    """report.json as one table (a row per stage) and the run's rates, losses and folder."""
    from rich.console import Console

    con = Console()
    con.print(summary_table(report))
    fp = report.get("f_pipeline_predicted")
    loss = report.get("loss")
    # a loss that was not measured is said so: never a 0 that nobody counted
    loss_text = "loss unknown" if loss is None else (
        f"loss {100 * loss:.1f} % ({report.get('frames_lost', '?')} of {report.get('frames_expected', '?')} frames)")
    con.print(f"frames in {report.get('frames_in')}, out {report.get('frames_out')} "
              f"(strided {report.get('frames_strided')}), {loss_text}, "
              f"f_in {_hz(report.get('f_in', 0))}, f_out {_hz(report.get('f_out', 0))}, "
              f"f_pipeline {_hz(fp)} (bottleneck {report.get('bottleneck')})")
    causes = _loss_causes(report.get("loss_breakdown"))
    if causes:
        con.print(f"loss by cause: {causes}")
    src = report.get("source") or {}
    if src.get("lost_before_source"):  # a live ROS 2 camera's gaps in its sequence numbers
        con.print(f"lost before the source: {src['lost_before_source']} frames (publishers' sequence numbers)")
    for note in [src.get("salvaged"), *(src.get("warnings") or [])]:  # a cut bag, a missing ground truth
        if note:
            con.print(f"source: {note}", markup=False)
    for name, st in report.get("stages", {}).items():  # what a calibrated front end settled on
        cal = (st.get("info") or {}).get("calibration")
        if cal:
            con.print(calibration_line(name, cal), markup=False)
    if report.get("status") == "failed":
        con.print(f"the run FAILED: {report.get('failure')}", markup=False)
    con.print(f"run folder: {report.get('run_dir')}")


def calibration_line(stage: str, cal: dict[str, Any]) -> str:
    """One line of what a calibrated front end settled on (report.json stages.<stage>.info)."""
    if cal.get("ready_from_frame", -1) < 0:
        return (f"{stage}: not calibrated: too few places seen a shortest loop ago "
                f"({cal.get('min_revisit_s')} s) to judge a revisit; no loop closure")
    head = (f"{stage}: calibrated from frame {cal['ready_from_frame']}: unrelated places score "
            f"{cal.get('unrelated_mean')} +- {cal.get('unrelated_sd')}, a revisit needs >= {cal.get('score_needed')} "
            f"(z >= {cal['z_min']}) over {cal['sequence_frames'] + 1} consistent frames; ")
    if not cal.get("revisit_seen"):
        return head + "no revisit seen in this run"
    merged = cal.get("templates_merged", 0)
    return (head + f"{cal['closures']} loop closures from frame {cal['first_closure_frame']}"
            + (f", {merged} templates found to be places already known" if merged else ""))


def _hz(value: float | None) -> str:
    """A rate as the summary prints it; n/a where nothing was measured."""
    return "n/a" if value is None else f"{value:.2f} Hz"


def _loss_causes(breakdown: dict[str, Any] | None) -> str:
    """One line of report.json's ``loss_breakdown``: the source's losses, each stage's refused /
    dropped messages, and what no counter explains."""
    if not breakdown:
        return ""
    parts = [f"source: {cause} {n}" for cause, n in (breakdown.get("source") or {}).items() if n]
    for stage, b in (breakdown.get("stages") or {}).items():
        parts += [f"{stage} {what.replace('_', ' ')} {n}" for what, n in b.items() if n]
    if breakdown.get("unattributed"):
        parts.append(f"in flight or lost while restarting {breakdown['unattributed']}")
    return "; ".join(parts)


def print_evaluation(ev: dict[str, Any]) -> None:
    """evaluation.json in a few lines: trajectory, odometry and map errors, loop closures."""
    from ..evaluation import METRICS, closures_line

    def m(d: dict[str, Any], key: str) -> str:
        return "n/a" if d.get(key) is None else f"{d[key]:.3f} m"

    t, o, p = ev.get("trajectory_ape", {}), ev.get("odometry_ape", {}), ev.get("map_paper", {})
    print(f"trajectory APE (SE(2)-aligned) mean {m(t, 'mean_m')} (max {m(t, 'max_m')}); "
          f"wheel odometry alone: APE mean {m(o, 'mean_m')}")
    print(f"  {METRICS['ape']}")
    print(f"map nodes {ev.get('map_nodes', 0)}: paper metric mean {m(p, 'mean_m')} (max {m(p, 'max_m')})")
    print(f"  {METRICS['paper']}")
    if ev.get("ground_truth_offset_s"):
        print(f"ground truth stamps shifted by {ev['ground_truth_offset_s']:.3f} s")
    if "map_trajectory_ape" in ev:
        print(f"trajectory on the final map (trajectory_map.tum) APE mean {ev['map_trajectory_ape']['mean_m']:.3f} m "
              f"(max {ev['map_trajectory_ape']['max_m']:.3f})")
    rpe = ev.get("trajectory_rpe") or {}
    if rpe:
        print("trajectory RPE (the motion's error over a stretch of travel, mean): "
              + ", ".join(f"{v['mean_m']:.3f} m over {v['delta_m']:g} m" for v in rpe.values() if v.get("mean_m") is not None))
    if "loop_closures" in ev:
        print(closures_line(ev["loop_closures"]))
        pr = ev["loop_closures"].get("precision_recall")
        if pr:
            ps, rs = zip(*pr["recall_at_precision"].items(), strict=True)
            print(f"  precision-recall by confidence: area {pr['area']:.2f}; recall at precision "
                  f"{' / '.join(ps)}: {' / '.join(f'{r:.2f}' for r in rs)} (pr_curve.png)")
    print("evaluation.json and map.png written")


def compare_tables(table: dict, radius: float = 1.0) -> tuple[Any, Any]:
    """compare_runs' table, a column per pipeline and a row per figure (n/a: not measurable in this
    run; -: does not apply), and each pipeline's per-stage latency, a row per stage."""
    from ..evaluation.compare import BRANCHES, COLUMNS
    from ..runtime.monitor import figure

    def header(name: str, row: dict) -> str:  # "NeoSLAM (default)" on two lines
        label = str(row.get("label", name)).replace(" (", "\n(")
        return label + ("\n= default" if row.get("same_as_default") else "")

    def cell(v: Any) -> str:
        return "n/a" if v is None else figure(v) if isinstance(v, float) else str(v)

    t = _table(f"The same stream; a closure is correct within {radius:g} m",
               "n/a: not measured in this run (no ground truth, or no revisit to recall); -: does not "
               "apply; APE on map: every frame on the final map (trajectory_map.tum)")
    t.add_column("", no_wrap=True, min_width=max(len(short) for _, short in COLUMNS))
    for name, row in table.items():
        t.add_column(header(name, row), justify="right", no_wrap=True)
    for key, short in COLUMNS:
        t.add_row(short, *[cell(row.get(key)) if key in row or name != "odometry" else "-"
                           for name, row in table.items()])
    prefixes = {key: prefix for key, _label, _sub, prefix in BRANCHES}
    per_stage: dict[str, dict[str, Any]] = {}
    for name, row in table.items():
        for stage, tau in (row.get("stage_tau_p50_ms") or {}).items():
            p = prefixes.get(name, "")
            per_stage.setdefault(stage[len(p):] if p and stage.startswith(p) else stage, {})[name] = tau
    branches = [n for n, row in table.items() if row.get("stage_tau_p50_ms")]
    lat = _table("per-stage latency (tau p50, ms)")
    lat.add_column("stage", no_wrap=True, min_width=max([5, *map(len, per_stage)]))
    for name in branches:
        lat.add_column(header(name, table[name]), justify="right", no_wrap=True)
    for stage, taus in per_stage.items():
        lat.add_row(stage, *["-" if taus.get(n) is None else figure(taus[n]) for n in branches])
    return t, lat


def print_compare(table: dict, radius: float = 1.0) -> None:
    """The comparison's two tables (:func:`compare_tables`)."""
    from rich.console import Console

    con = Console()
    for t in compare_tables(table, radius):
        con.print(t)


def error(message: Any, code: int) -> int:
    """Print ``error: message`` on stderr; the command's exit code."""
    print(f"error: {message}", file=sys.stderr)
    return code
