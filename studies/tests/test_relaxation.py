"""studies/relaxation.py: the rule that chose the experience map's relaxation, by hand."""

from relaxation import choose


def test_the_relaxation_rule_by_hand():
    # the rule on made-up rows: the lowest mean final map among the relaxations whose online error
    # is within 5 % of least squares' on every validation part
    def rows(**cells):
        return {name: {"online_m": on, "final_map_m": final} for name, (on, final) in cells.items()}

    # "walk_a": the best final maps (mean 1.0) but online 1.06 x least squares' on part b: out;
    # "walk_b": online 1.04 x and 0.5 x, mean final map 1.5 against least squares' 2.0: chosen;
    # under the first wording (within 5 % of the best online on every part: 1.0 on a, 0.5 on b)
    # nothing but walk_b is within 5 % on b, and walk_b is 1.04 x the best on a: eligible too
    res = {"validation": ["a", "b"], "parts": {
        "a": rows(least_squares=(1.0, 2.0), walk_a=(1.0, 1.0), walk_b=(1.04, 1.0)),
        "b": rows(least_squares=(1.0, 2.0), walk_a=(1.06, 1.0), walk_b=(0.5, 2.0))}}
    got = choose(res)
    assert got["eligible"] == ["least_squares", "walk_b"] and got["chosen"] == "walk_b"
    assert got["mean_final_map_m"] == {"least_squares": 2.0, "walk_a": 1.0, "walk_b": 1.5}
    assert got["eligible_within_best_online"] == ["walk_b"]
    # nothing better than the incumbent: it stays
    res["parts"]["b"]["walk_b"]["online_m"] = 1.1
    assert choose(res)["chosen"] == "least_squares"
