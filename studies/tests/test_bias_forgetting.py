"""studies/bias_forgetting.py: the rule that chose the yaw-rate bias's forgetting, by hand."""

import pytest
from bias_forgetting import FORGET, choose


def test_the_bias_forgetting_rule_by_hand():
    # the rule on made-up rows: mean online error relative to 120 s's, among the forgettings whose
    # final map stays within 5 % of 120 s's on every part; ties within 0.01 go to the longer
    # forgetting
    def part(online: dict, final: dict) -> dict:
        return {f"{f:g}": {"online_m": online.get(f, 1.0), "final_map_m": final.get(f, 1.0)} for f in FORGET}

    # 5 s: online 0.5 and 0.7 of 120 s's (score 0.6) but one final map 1.06 x: not eligible;
    # 15 s: 0.8 and 0.8 (score 0.8); 30 s: 0.81 and 0.8 (0.805, a tie with 15 s): 30 s wins the tie
    valid = {"a": part({5.0: 0.5, 15.0: 0.8, 30.0: 0.81}, {5.0: 1.06}),
             "b": part({5.0: 0.7, 15.0: 0.8, 30.0: 0.80}, {})}
    got = choose(valid)
    assert got["eligible"]["5"] is False and got["scores"]["5"] == pytest.approx(0.6)
    assert got["scores"]["30"] == pytest.approx(0.805) and got["forget_s"] == 30.0
    # within the 5 % the same 5 s wins outright
    valid["a"]["5"]["final_map_m"] = 1.05
    assert choose(valid)["forget_s"] == 5.0
