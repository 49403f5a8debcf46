"""The README's table of bench/results/generalisation.json: each data set with the single
default, the paper profile and RatSLAM side by side (``python bench/generalisation.py --table``)."""

from __future__ import annotations

from typing import Any


def _pr(r: dict[str, Any] | None) -> str:
    if not r:
        return "—"
    p = "—" if r.get("precision") is None else f"{r['precision']:.2f}"
    return f"{p} / {r['recall']:.2f}"


def _mean(rows: list[dict[str, Any]]) -> dict[str, Any]:
    ps = [r["precision"] for r in rows if r["precision"] is not None]
    return {"precision": sum(ps) / len(ps) if ps else None, "recall": sum(r["recall"] for r in rows) / len(rows)}


def table(res: dict[str, Any]) -> str:
    test = res.get("test", {})
    lines = ["| data set (held out) | figure | default | paper profile | RatSLAM |", "|---|---|---|---|---|"]
    for label, key in (("synthetic world 0, the default route", "route"),
                       ("synthetic world 2, its route with the back end", "route_2")):
        route = res.get(key)
        if route:
            d, p, r = route["default"], route["paper"], route["ratslam"]
            lines.append(f"| {label} | closure precision / recall | {_pr(d)} | {_pr(p)} | {_pr(r)} |")
            lines.append(f"| | APE online (floor {d['online_floor_m']:.2f} m) / on the final map | "
                         f"{d['ape_mean_m']:.2f} / {d['ape_on_final_map_m']:.2f} m | "
                         f"{p['ape_mean_m']:.2f} / {p['ape_on_final_map_m']:.2f} m | "
                         f"{r['ape_mean_m']:.2f} / {r['ape_on_final_map_m']:.2f} m |")
    for label, prefix in (("synthetic world 2, the front end alone", "synthetic:2"),
                          ("Nordland summer → winter (test subset)", "nordland:0")):
        if prefix in test:
            t = test[prefix]
            lines.append(f"| {label} | precision / recall | {_pr(t['default'])} | {_pr(t['paper'])} | {_pr(t['ratslam'])} |")
    for label, prefix in (("sparse two-lap stand-ins, no stamps (4 worlds)", "sparse"),
                          ("the same, second lap under other light (4 worlds)", "hard"),
                          ("Gardens Point Walking, real, the held-out halves (3 pairs)", "gardens")):
        parts = [v for k, v in test.items() if k.startswith(prefix + ":") and not k.endswith(":a")]
        if parts:
            cells = [_pr(_mean([v[n] for v in parts])) for n in ("default", "paper", "ratslam")]
            lines.append(f"| {label} | mean precision / recall | {' | '.join(cells)} |")
    tuc = res.get("tuc")
    # the whole run is not held out (its first half chose the back end's constants); its second half
    # run alone is
    for label, suffix in (("TU Chemnitz corridor, second half run alone (back end)", "_second_half"),
                          ("the whole corridor run (not held out: its first half chose constants)", "")):
        if tuc and "default" + suffix in tuc:
            d, p = tuc["default" + suffix], tuc["paper" + suffix]
            lines.append(f"| {label} | map error / odometry's | "
                         f"{d['map_mean_m']:.1f} / {d['odometry_mean_m']:.1f} m ({d['map_vs_odometry']:.0%}) | "
                         f"{p['map_mean_m']:.1f} m ({p['map_vs_odometry']:.0%}) | — |")
    return "\n".join(lines)
