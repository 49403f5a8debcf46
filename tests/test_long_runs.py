"""A route driven again and again (docs/long_runs.md): the experience map held at a bounded density
(map_pruning.py) and D's revisits merged into the places they matched (revisit_merge.py), worked by
hand; their states through a save and a load; the paper's profile without either."""

from __future__ import annotations

import math

import numpy as np
import pytest

from neoslam_stream.algorithms.calibration import PlatformConfig
from neoslam_stream.algorithms.ratslam.experience_map import ExperienceMap
from neoslam_stream.algorithms.ratslam.map_pruning import (
    compose,
    inverse,
    link_pose,
    merges,
    relative,
    settled,
)
from neoslam_stream.algorithms.ratslam.pose_cells import CREATE_EDGE, CREATE_NODE, SET_NODE
from neoslam_stream.algorithms.revisit_merge import DROP, EXPIRE, INDEX, RevisitMerge, Stored
from neoslam_stream.algorithms.spatial_view import SpatialViewCells, SpatialViewConfig
from neoslam_stream.config import load_config


# ------------------------------------------------------------------------------ the experience map
def _square(prune_m: float) -> ExperienceMap:
    """Experiences 0 (0, 0, 0), 1 (2, 0, 0), 2 (2, 2, pi/2), 3 (0, 2, pi), 4 (0, 0.3, -pi/2) by exact
    odometry, then the robot turns back to heading 0 at (0, 0) and recognises experience 0: the loop
    link 4 -> 0 agrees with the others, so the solve moves nothing (the map was right)."""
    em = ExperienceMap(exp_initial_em_deg=0, relaxation="least_squares", prune_m=prune_m)
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    for k, (v, w) in enumerate([(2.0, 0.0), (2.0, math.pi / 2), (2.0, math.pi / 2), (1.7, math.pi / 2)]):
        em.on_odo(v, w, 1.0)  # turn first, then drive
        em.on_action(CREATE_NODE, k, k + 1, 0.0)
    em.on_odo(0.3, 0.0, 1.0)
    em.on_odo(0.0, math.pi / 2, 1.0)
    em.on_action(CREATE_EDGE, 4, 0, 0.0)
    return em


POSES = {0: (0.0, 0.0, 0.0), 1: (2.0, 0.0, 0.0), 2: (2.0, 2.0, math.pi / 2), 3: (0.0, 2.0, math.pi),
         4: (0.0, 0.3, -math.pi / 2)}


def _close(a, b) -> bool:
    """Poses (x, y, theta) equal to 1e-9, headings modulo a whole turn."""
    return all(math.isclose(u, v, abs_tol=1e-9) for u, v in zip(a[:2], b[:2], strict=True)) and \
        abs(math.remainder(a[2] - b[2], 2 * math.pi)) < 1e-9


def test_an_experience_closer_than_the_spacing_merges_into_the_older_one():
    # without pruning: five experiences where the odometry put them, five links
    plain = _square(0.0)
    assert plain.n_experiences == 5 and plain.n_links == 5
    assert all(_close(plain.node_poses()[e], p) for e, p in POSES.items())
    # with a spacing of 0.5 m: experience 4 lies 0.3 m from experience 0, the older one: merged
    em = _square(0.5)
    assert em.ids == [0, 1, 2, 3] and em.n_links == 4
    into, dx, dy, dth = em.merged[4]
    # its pose in 0's frame, by hand: 0.3 m along 0's y axis, turned by -pi/2
    assert into == 0 and _close((dx, dy, dth), (0.0, 0.3, -math.pi / 2))
    # nothing moved: the survivors where they were, the merged experience where it was
    assert all(_close(em.node_poses()[e], p) for e, p in POSES.items())
    # 3 -> 4 now goes 3 -> 0, saying where 0 lies in 3's frame: 2 m to its left (3 faces -x, 0
    # lies 2 m towards -y), turned by a half turn; 4 -> 0 joined 0 to itself and is gone
    links = {(a, b): (d, h, f) for a, b, d, h, f, _ in em.links}
    assert set(links) == {(0, 1), (1, 2), (2, 3), (3, 0)}
    d, h, f = links[(3, 0)]
    assert math.isclose(d, 2.0) and math.isclose(h, math.pi / 2) and math.isclose(abs(f), math.pi)
    assert _close(link_pose(d, h, f), relative(POSES[3], POSES[0]))
    # the export says where a frame recorded on 4 lies
    assert em.export()["merged"] == [{"id": 4, "into": 0, "dx": dx, "dy": dy, "dtheta": dth}]


def test_an_action_naming_a_merged_experience_arrives_where_it_lay():
    """The pose cells do not read the map, so they may name experience 4 again: a link to it goes
    to 0 with 4's offset taken out, and dead reckoning starts at 4's pose, as the map without
    pruning does (same robot pose, same link measurement once expressed on 0)."""
    runs = {}
    for prune in (0.0, 0.5):
        em = _square(prune)
        em.on_odo(2.0, 0.0, 1.0)  # from 0 round the square to experience 2's place
        em.on_odo(2.0, math.pi / 2, 1.0)
        em.on_action(SET_NODE, 0, 2, 0.0)
        em.on_odo(2.0, math.pi / 2, 1.0)  # on to 3's place and down to 4's, facing as 4 does
        em.on_odo(1.7, math.pi / 2, 1.0)
        em.on_action(CREATE_EDGE, 2, 4, 0.0)
        runs[prune] = em
    plain, pruned = runs[0.0], runs[0.5]
    assert _close(pruned.robot_pose(), plain.robot_pose()) and _close(plain.robot_pose(), POSES[4])
    (d, h, f), = [(d, h, f) for a, b, d, h, f, _ in plain.links if (a, b) == (2, 4)]
    (d2, h2, f2), = [(d, h, f) for a, b, d, h, f, _ in pruned.links if (a, b) == (2, 0)]
    o = pruned.merged[4][1:]
    assert _close(link_pose(d2, h2, f2), compose(link_pose(d, h, f), inverse(o)))
    assert pruned.current == 0 and pruned.n_experiences == 4


def test_a_stretch_of_dead_reckoning_is_not_pruned_until_a_loop_settles_it():
    # a chain 0 - 1 - 2 - 3 (bridges only) and a triangle 3 - 4 - 5 - 3; 6 hangs off 5 by 0.2 m
    lfrom, lto = np.array([0, 1, 2, 3, 4, 5, 5]), np.array([1, 2, 3, 4, 5, 3, 6])
    ld = np.array([1.0, 1.0, 0.4, 1.0, 1.0, 1.0, 0.2])
    assert settled(7, lfrom, lto, ld, 0.5).tolist() == [False, False, True, True, True, True, True]
    assert settled(7, lfrom, lto, ld, 0.0).tolist() == [False, False, False, True, True, True, False]


def test_only_an_earlier_visit_takes_a_settled_experience():
    """Experiences 0..4 of one visit 0.2 m apart (made 1 s apart), 5 and 6 of a later visit (made
    at 100 s and 130 s) 0.1 m from 1 and from 3, with a spacing of 0.5 m, an earlier visit at least
    40 s before and experiences merged once made by 120 s: one visit's experiences stay as they are,
    5 merges into 1 (the nearest of the earlier visit's), 6 is too young yet."""
    x = np.array([0.0, 0.2, 0.4, 0.6, 0.8, 0.2, 0.6])
    y = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.1, 0.1])
    born = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 100.0, 130.0])
    every = np.ones(7, dtype=bool)
    assert merges(x, y, born, every, -1, 0.5, gap_s=40.0, before=120.0) == [(5, 1)]
    assert merges(x, y, born, every, -1, 0.5, gap_s=40.0) == [(5, 1), (6, 3)]
    # without the visits told apart, the survivors are 0.5 m apart whichever visit made them
    assert merges(x, y, born, every, -1, 0.5) == [(1, 0), (2, 0), (4, 3), (5, 0), (6, 3)]
    assert merges(x, y, born, every, 5, 0.5, gap_s=40.0) == [(6, 3)]  # the current one stays


def test_a_pruned_map_is_saved_loaded_and_goes_on_as_before():
    em = _square(0.5)
    copy = ExperienceMap(exp_initial_em_deg=0, relaxation="least_squares", prune_m=0.5)
    copy.load_state_dict(em.state_dict())
    for m in (em, copy):
        m.on_odo(1.0, 0.0, 1.0)
        m.on_action(CREATE_NODE, 0, 5, 0.0)
        m.on_odo(0.0, math.pi, 1.0)
        m.on_odo(1.0, 0.0, 1.0)
        m.on_action(CREATE_EDGE, 5, 4, 0.0)
    assert copy.export() == em.export() and copy.robot_pose() == em.robot_pose()


def test_the_default_prunes_and_merges_and_the_paper_profile_does_neither():
    default, paper = load_config("default"), load_config("paper")
    em = default.back_end().experience_map  # 0.3 m/s, a 23.7 m shortest loop
    assert default.spatial_view.merge_revisits and math.isclose(em.prune_m, 0.6)
    assert math.isclose(em.prune_gap_s, 23.7 / 0.6) and math.isclose(em.prune_age_s, 23.7 / 0.3)
    assert not paper.spatial_view.merge_revisits and paper.back_end().experience_map.prune_m == 0.0
    with pytest.raises(ValueError, match="index_revisits"):
        SpatialViewConfig(calibration={"enabled": True}, merge_revisits=True)
    with pytest.raises(ValueError, match="prune_m"):
        ExperienceMap(prune_m=0.5, openratslam_compat=True)


# ------------------------------------------------------------------------------ D's revisits
def test_the_revisit_bookkeeping_by_hand():
    m = RevisitMerge()
    m.close(0, False)                                 # a new place, no candidate: indexed at once
    assert m.settle(5, 3) == [(0, INDEX)]
    m.close(1, True)                                  # every frame closed: a known place
    assert m.settle(6, 3) == [(1, DROP)]
    assert m.may_hold(10, 0.5, 3)                     # stood out on its own: held
    m.register(2, 10, held=True)
    m.close(2, False)
    assert not m.may_hold(14, 0.5, 3)                 # a hold lasts one stretch (3 frames)
    m.end_hold()
    assert not m.may_hold(15, -0.1, 3)                # stood out less: makes a template
    m.register(3, 15, held=False)
    m.close(3, False)
    assert m.settle(12, 3) == []                      # 2 may still be confirmed (until frame 13)
    assert m.settle(13, 3) == [(2, EXPIRE)]           # no closure came: a held view expired
    m.confirm(3)                                      # a closure confirmed 3: merged
    assert m.settle(14, 3) == [(3, DROP)]
    assert m.second_view(7) and not m.second_view(7)  # one expired view per place
    copy = RevisitMerge()
    copy.load_state_dict(m.state_dict())
    assert copy.state_dict() == m.state_dict()
    s = Stored()
    for v in "abc":
        s.append(v)
    s.forget(1)
    assert len(s) == 3 and s[-1] == "c" and 1 not in s and s.keys() == [0, 2]
    with pytest.raises(KeyError):
        s[1]


def _places(n: int, rng: np.random.Generator) -> list[np.ndarray]:
    return [np.sort(rng.choice(65536, 512, replace=False)) for _ in range(n)]


def _noisy(cols: np.ndarray, rng: np.random.Generator, keep: float) -> np.ndarray:
    k = int(round(keep * len(cols)))
    return np.unique(np.concatenate([rng.choice(cols, k, replace=False), rng.choice(65536, len(cols) - k)]))


def _d(merge: bool) -> SpatialViewCells:
    cfg = SpatialViewConfig(calibration={"enabled": True}, index_revisits=False, merge_revisits=merge)
    return SpatialViewCells(cfg, platform=PlatformConfig(speed_mps=0.2, shortest_loop_m=20.0))


def test_a_route_driven_four_times_keeps_what_it_kept_after_the_first_drive():
    """Four drives of 80 places, one frame a second at 0.2 m/s: the evidence needs L = 3 frames,
    so each revisit stretch's first frames are refused. Without the merge they make templates on
    every drive and D keeps an interval per interval made; with it, a refused frame that stood out
    keeps the current template and a confirmed interval merges into its place: the later drives
    make (almost) no template, D keeps what it kept after the first drive (plus the recent ones),
    and they close as many frames; a save mid-drive and a load give the same decisions."""
    rng = np.random.default_rng(11)
    places = _places(80, rng)
    frames = [_noisy(p, rng, 0.9) for p in places] + [_noisy(p, rng, 0.6) for _ in range(3) for p in places]
    runs = {}
    for merge in (False, True):
        d = _d(merge)
        out = [d.compute(f, stamp=float(i)) for i, f in enumerate(frames)]
        runs[merge] = (d, out)
    (plain, out0), (merged, out1) = runs[False], runs[True]
    assert merged.calibration.sequence_frames == 3

    def drive(out, n):
        seen = {r["id"] for r in out[:80 * n]}
        return (sum(r["is_loop_closure"] for r in out[80 * n:80 * n + 80]),
                len({r["id"] for r in out[80 * n:80 * n + 80]} - seen))

    for n in (2, 3):
        closed0, new0 = drive(out0, n)
        closed1, new1 = drive(out1, n)
        assert new0 >= 3 and new1 <= 1 < new0          # templates on every drive, without the merge
        assert closed1 >= closed0 - 3 and closed1 >= 60
    assert plain.n_stored == plain.n_intervals         # every interval kept
    assert merged.n_stored <= len(merged.indexed) + 3 and len(merged.indexed) <= 84
    # held frames carry the template the robot had: the frame before's
    held = merged.merge.counts["held"]
    assert held > 0 and merged.merge.counts["merged"] > 0
    half = _d(True)
    for i, f in enumerate(frames[:170]):
        half.compute(f, stamp=float(i))
    resumed = _d(True)
    resumed.load_state_dict(half.state_dict())
    assert [resumed.compute(f, stamp=float(170 + i)) for i, f in enumerate(frames[170:])] == out1[170:]
    with pytest.raises(ValueError, match="merge_revisits"):
        _d(False).load_state_dict(merged.state_dict())


def test_a_pruned_map_and_merged_intervals_go_through_a_map_file_and_on(tmp_path):
    """What `neoslam map export` packs and `--map` loads (each stage's state through the map file's
    msgpack) of a pruned map and of D with merged revisits: loaded into new stages for a new
    session, both go on exactly as the stages that saved them."""
    from neoslam_stream.nodes.ratslam import ExperienceMapNode
    from neoslam_stream.runtime.checkpoint import load_state_file, save_state_file

    params = {"exp_initial_em_deg": 0, "relaxation": "least_squares", "prune_m": 0.5}
    saved = ExperienceMapNode(**params)
    saved.em = _square(0.5)
    save_state_file(tmp_path / "experience_map.state", saved.state_dict())
    loaded = ExperienceMapNode(**params)
    loaded.load_state_dict(load_state_file(tmp_path / "experience_map.state"))
    loaded.new_session()
    assert loaded.em.merged == saved.em.merged and loaded.em.ids == [0, 1, 2, 3]
    for em in (saved.em, loaded.em):
        em.on_odo(2.0, 0.0, 1.0)
        em.on_odo(2.0, math.pi / 2, 1.0)
        em.on_action(SET_NODE, 0, 2, 0.0)
        em.on_odo(2.0, math.pi / 2, 1.0)
        em.on_odo(1.7, math.pi / 2, 1.0)
        em.on_action(CREATE_EDGE, 2, 4, 0.0)  # the merged experience, named again
    assert loaded.em.export() == saved.em.export() and _close(loaded.em.robot_pose(), POSES[4])

    rng = np.random.default_rng(12)
    places = _places(60, rng)
    frames = [_noisy(p, rng, 0.9) for p in places] + [_noisy(p, rng, 0.6) for _ in range(2) for p in places]
    whole = _d(True)
    ref = [whole.compute(f, stamp=float(i)) for i, f in enumerate(frames)]
    first = _d(True)
    for i, f in enumerate(frames[:100]):
        first.compute(f, stamp=float(i))
    assert first.merge.counts["held"] > 0
    save_state_file(tmp_path / "D.state", first.state_dict())
    second = _d(True)
    second.load_state_dict(load_state_file(tmp_path / "D.state"))
    assert [second.compute(f, stamp=float(100 + i)) for i, f in enumerate(frames[100:])] == ref[100:]
