"""studies/visual_odometry_choices.py: the rule that kept each step of the default's visual odometry,
by hand."""

from visual_odometry_choices import BEFORE, STEPS, choose, variants


def _world(**final: float) -> dict:
    return {name: {"online_m": 1.0, "final_map_m": value} for name, value in final.items()}


def test_each_step_stands_on_the_ones_before():
    v = variants()
    assert v["before"] == BEFORE
    assert v["normal_flow"] == {**BEFORE, **{k: val for change in STEPS.values() for k, val in change.items()}}


def test_the_visual_odometry_rule_by_hand():
    # subpixel: mean 2.0 -> 1.8, world b unchanged: kept. rotation_check: mean down (1.8 -> 1.55)
    # but world b 2.2 / 2.0 = 1.1 x: left out, so normal_flow (replayed on top of it) is not tried
    got = choose({"a": _world(before=2.0, subpixel=1.6, rotation_check=0.9, normal_flow=0.5),
                  "b": _world(before=2.0, subpixel=2.0, rotation_check=2.2, normal_flow=0.5)})
    assert got["steps"]["subpixel"]["kept"] and got["steps"]["subpixel"]["mean_ratio"] == 0.9
    assert got["steps"]["rotation_check"]["final_map_vs_subpixel"]["b"] == 1.1
    assert not got["steps"]["rotation_check"]["kept"]
    assert got["steps"]["normal_flow"].startswith("not tried")
    assert got["visual_odometry"] == {**BEFORE, "subpixel": True}
    # a step that lowers every world is kept, and the next is judged against it
    got = choose({"a": _world(before=2.0, subpixel=1.9, rotation_check=1.8, normal_flow=1.7)})
    assert all(s["kept"] for s in got["steps"].values())
    assert got["steps"]["normal_flow"]["final_map_vs_rotation_check"] == {"a": round(1.7 / 1.8, 3)}
