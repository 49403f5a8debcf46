"""The command line's tables read at 80 columns (a pipe, a narrow terminal): every stage's name
whole, every column with its values, nothing cut to an ellipsis."""

from __future__ import annotations

import io
import time

import pytest
from rich.console import Console

from neoslam_stream.cli.report import compare_tables, summary_table
from neoslam_stream.runtime.monitor import figure, stats_table

STAGES = ["A", "B", "C", "D", "pose_cells", "experience_map", "recorder"]


def render(table, width: int = 80) -> list[str]:
    con = Console(width=width, record=True, file=io.StringIO(), color_system=None)
    con.print(table)
    return con.export_text().splitlines()


def cells(table) -> list[list[str]]:
    """The table's rows as the strings it holds, a list per row (first cell: the row's name)."""
    cols = [[str(c) for c in col._cells] for col in table.columns]
    return [list(r) for r in zip(*cols, strict=True)]


def assert_readable(table, width: int = 80) -> None:
    """Each row's name starts its line whole and its values follow it, in order, each whole; no
    cell is empty and nothing is cut."""
    lines = render(table, width)
    assert not any("…" in line for line in lines), "\n".join(lines)
    assert all(len(line) <= width for line in lines)
    body = lines[next(i for i, x in enumerate(lines) if "─" in x) + 1:]  # below the header's rule
    for row in cells(table):
        assert all(row), row  # every column has a value
        line = next((x for x in body if x.strip().startswith(row[0] + " ") or x.strip() == row[0]), None)
        assert line is not None, f"{row[0]!r} is not whole in:\n" + "\n".join(lines)
        rest = line.strip()[len(row[0]):]
        for value in row[1:]:
            assert value in rest, f"{value!r} of {row[0]!r} is cut in {line!r}"
            rest = rest[rest.index(value) + len(value):]


def _stage(received=216002, processed=108001, tau=1234.5):
    return {"started": time.time() - 900, "received": received, "processed": processed, "tau_p50_ms": tau,
            "tau_p95_ms": 12.345, "queue_p50_ms": 0.123, "inputs": {"image": {"evicted": 123456}}, "errors": 3000,
            "cpu_percent": 195.0, "pss_mb": 1234.0}


@pytest.mark.parametrize("prefix", ["", "pp_", "rs_"])
def test_the_live_table_keeps_every_name_and_value_at_80_columns(prefix):
    stats = {"source": {"frames_in": 108001, "errors": 0}, **{prefix + s: _stage() for s in STAGES}}
    table = stats_table(stats, "neoslam run r0123abcd")
    assert [r[0] for r in cells(table)] == ["source", *sorted(prefix + s for s in STAGES)]
    # the source's row has no rate or service time of its own: the stages' rows are checked whole
    lines = render(table)
    assert not any("…" in line for line in lines)
    for row in cells(table)[1:]:
        line = next(x for x in lines if x.strip().startswith(row[0] + " "))
        assert line.split() == row, line


def test_the_scan_sees_a_cut_name():
    # the check above must be able to fail: at 40 columns the same table cuts names
    stats = {s: _stage() for s in STAGES}
    with pytest.raises(AssertionError):
        assert_readable(stats_table(stats), width=40)


def test_the_run_summary_keeps_every_name_and_value_at_80_columns():
    stages = {p + s: {"processed": 108001, "tau_p50_ms": 12.3, "tau_p95_ms": 1234.0, "dropped": 123456, "errors": 3}
              for p in ("", "pp_", "rs_") for s in STAGES}
    assert_readable(summary_table({"run": "compare-2445", "topology": "pipeline", "mode": "lossless",
                                   "stages": stages}))


def _branch(label, prefix, **over):
    stages = (["A", "B", "C", "D"] if prefix != "rs_" else ["local_view"]) + ["pose_cells", "experience_map", "recorder"]
    row = {"label": label, "same_as_default": False, "frames_processed": 2445, "trajectory_ape_mean_m": 0.8312,
           "trajectory_ape_max_m": 2.5, "map_trajectory_ape_mean_m": 0.13, "map_paper_mean_m": 4.42,
           "map_paper_max_m": 9.9, "map_nodes": 1234, "loop_closures": 567, "loop_correct": 500,
           "loop_precision": 1.0, "loop_recall": None, "loop_radius_m": 1.0,
           "stage_tau_p50_ms": {prefix + s: 1.234 for s in stages}}
    return {**row, **over}


def test_the_comparison_keeps_every_name_and_value_at_80_columns():
    table = {"neoslam": _branch("NeoSLAM (default)", ""), "neoslam_paper": _branch("NeoSLAM (paper)", "pp_"),
             "ratslam": _branch("RatSLAM", "rs_", loop_recall=0.07, map_trajectory_ape_mean_m=None),
             "odometry": {"label": "odometry", "trajectory_ape_mean_m": 5.09, "trajectory_ape_max_m": 9.1}}
    figures, latency = compare_tables(table)
    assert_readable(figures)
    assert_readable(latency)
    rows = {r[0]: r[1:] for r in cells(figures)}
    assert rows["recall"] == ["n/a", "n/a", "0.07", "-"]  # not measured, measured, does not apply
    assert rows["APE mean m"] == ["0.83", "0.83", "0.83", "5.09"]
    lat = {r[0]: r[1:] for r in cells(latency)}
    assert lat["local_view"] == ["-", "-", "1.23"] and lat["D"] == ["1.23", "1.23", "-"]  # prefixes gone


def test_the_paper_branch_that_is_the_default_says_so():
    table = {"neoslam": _branch("NeoSLAM (default)", ""), "neoslam_paper": _branch("NeoSLAM (paper)", "", same_as_default=True)}
    figures, _ = compare_tables(table)
    assert "= default" in "\n".join(render(figures))


@pytest.mark.parametrize(("value", "text"), [(0, "0"), (0.123, "0.12"), (12.345, "12.3"), (99.96, "100"),
                                             (1234.5, "1234"), (-2.5, "-2.50")])
def test_figures_take_at_most_four_characters_below_ten_thousand(value, text):
    assert figure(value) == text
