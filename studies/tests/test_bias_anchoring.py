"""studies/bias_anchoring.py: the rule that chose the anchoring's time constant, by hand."""

from bias_anchoring import ANCHOR_S, choose, loop_s, name, seconds


def _rows(values: dict[str, float], key: str) -> dict:
    return {name(a): {key: values.get(name(a), 1.0)} for a in ANCHOR_S}


def test_loop_is_one_shortest_loop_at_the_typical_speed():
    # the synthetic world's platform (configs/default.yaml): 23.7 m at 0.3 m/s; the TUC corridor's
    # (bench/settings/tuc.yaml): out to the end of 167 m and back at 0.4 m/s
    assert abs(loop_s("day:101") - 23.7 / 0.3) < 1e-9 and abs(loop_s("synthetic:1") - 23.7 / 0.3) < 1e-9
    assert abs(loop_s("tuc:first") - 334.0 / 0.4) < 1e-9
    assert seconds("tuc:second", 100.0) == 100.0 and seconds("tuc:second", "loop") == loop_s("tuc:second")


def test_the_anchoring_rule_by_hand():
    # short parts: final maps against anchor_s 0's (1.0); 10 s is out on part s2 (1.06 > 1.05 x)
    short = {"s1": _rows({"0": 1.0, "10": 1.0, "30": 1.05, "100": 0.5, "loop": 0.5}, "final_map_m"),
             "s2": _rows({"0": 1.0, "10": 1.06, "30": 0.9, "100": 0.9, "loop": 1.2}, "final_map_m")}
    # the days' worst online laps: 10 s would win (0.15) but is not eligible, nor is loop (1.2 on
    # s2); 30 s scores 0.20 and 100 s 0.209 (within 5 % of 0.20: a tie, won by the longer)
    days = {"day:1": _rows({"0": 0.30, "10": 0.10, "30": 0.20, "100": 0.208, "loop": 0.1},
                           "online_worst_from_lap3_m"),
            "day:2": _rows({"0": 0.30, "10": 0.20, "30": 0.20, "100": 0.210, "loop": 0.1},
                           "online_worst_from_lap3_m")}
    got = choose({**days, **short})
    assert got["eligible"] == {"0": True, "10": False, "30": True, "100": True, "loop": False}
    assert got["scores"]["100"] == 0.209 and got["anchor_s"] == "100"
    # outside the tie (0.211 > 1.05 x 0.20) the lower score wins
    days["day:1"]["100"]["online_worst_from_lap3_m"] = 0.212
    assert choose({**days, **short})["anchor_s"] == "30"
    # loop eligible and tied with 30 s (0.205 <= 1.05 x 0.20): on the day it is 79 s, the longer
    short["s2"]["loop"]["final_map_m"] = 0.9
    days["day:1"]["loop"]["online_worst_from_lap3_m"] = days["day:2"]["loop"]["online_worst_from_lap3_m"] = 0.205
    assert choose({**days, **short})["anchor_s"] == "loop"
