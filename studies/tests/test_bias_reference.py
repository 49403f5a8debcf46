"""studies/bias_reference.py: the rule that chose which visit a return is compared with, by hand."""

from bias_reference import choose


def test_the_bias_reference_rule_by_hand():
    # latest is taken only if neither its online nor its final-map error exceeds 1.05 x first's on
    # any validation part
    def part(online: float, final: float) -> dict:
        return {"first": {"online_m": 1.0, "final_map_m": 2.0}, "latest": {"online_m": online, "final_map_m": final}}

    assert choose({"a": part(0.9, 2.1), "b": part(1.0, 2.0)})["reference"] == "latest"  # 1.05 x: still in
    got = choose({"a": part(0.9, 1.0), "b": part(1.06, 2.0)})
    assert got["reference"] == "first" and got["latest_vs_first"]["b"]["online_m"] == 1.06
    assert choose({"a": part(1.0, 2.2)})["reference"] == "first"
