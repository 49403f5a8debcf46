"""studies/bias_anchoring.py: the rule that chose the anchoring's time constant, by hand."""

from bias_anchoring import ANCHOR_S, choose


def _rows(values: dict[str, float], key: str) -> dict:
    return {f"{a:g}": {key: values.get(f"{a:g}", 1.0)} for a in ANCHOR_S}


def test_the_anchoring_rule_by_hand():
    # short parts: final maps against anchor_s 0's (1.0); 10 s is out on part s2 (1.06 > 1.05 x)
    short = {"s1": _rows({"0": 1.0, "10": 1.0, "30": 1.05, "100": 0.5}, "final_map_m"),
             "s2": _rows({"0": 1.0, "10": 1.06, "30": 0.9, "100": 0.9}, "final_map_m")}
    # the days' worst online laps: 10 s would win (0.15) but is not eligible; 30 s scores 0.20 and
    # 100 s 0.209 (within 5 % of 0.20: a tie, won by the longer time constant)
    days = {"day:1": _rows({"0": 0.30, "10": 0.10, "30": 0.20, "100": 0.208}, "online_worst_from_lap3_m"),
            "day:2": _rows({"0": 0.30, "10": 0.20, "30": 0.20, "100": 0.210}, "online_worst_from_lap3_m")}
    got = choose({**days, **short})
    assert got["eligible"] == {"0": True, "10": False, "30": True, "100": True}
    assert got["scores"]["100"] == 0.209 and got["anchor_s"] == 100.0
    # outside the tie (0.211 > 1.05 x 0.20) the lower score wins
    days["day:1"]["100"]["online_worst_from_lap3_m"] = 0.212
    assert choose({**days, **short})["anchor_s"] == 30.0
