"""A new session on a stored map (``neoslam map export`` then ``neoslam run --map``): the places of the
earlier session are recognised from the new session's first frames on, and its experiences and poses
lie on the earlier map, not on a branch drawn from where the earlier session ended.

Hand-worked cases for each part (D's stamps, the pose cells' relocalisation, the experience map's
join of two parts, the odometry gate), then the shipped default through processes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from neoslam_stream.algorithms.calibration import PlatformConfig
from neoslam_stream.algorithms.ratslam.actions import CREATE_EDGE, CREATE_NODE
from neoslam_stream.algorithms.ratslam.experience_map import ExperienceMap
from neoslam_stream.algorithms.ratslam.odometry_gate import OdometryGate
from neoslam_stream.algorithms.ratslam.pose_cells import PoseCellNetwork
from neoslam_stream.algorithms.spatial_view import SpatialViewCells, SpatialViewConfig

PLATFORM = PlatformConfig(speed_mps=0.3, shortest_loop_m=23.7, area_m=10.0)


# ---------------------------------------------------------------------------- D: stamps across sessions
def _places(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.choice(65536, 512, replace=False) for _ in range(n)]


def _visit(place: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A view of a place: a tenth of its cells replaced by others."""
    keep = rng.permutation(place)[: len(place) * 9 // 10]
    return np.unique(np.concatenate([keep, rng.choice(65536, len(place) - len(keep), replace=False)]))


def _drive(d: SpatialViewCells, places: list[np.ndarray], seed: int) -> list[dict]:
    """One pass over the places at 10 Hz, stamps from 0 (a session's own clock)."""
    rng = np.random.default_rng(seed)
    return [d.compute(_visit(p, rng), stamp=0.1 * i) for i, p in enumerate(places)]


def test_a_new_session_recognises_the_stored_places_once_its_evidence_spans_sequence_m():
    cfg = SpatialViewConfig(calibration={"enabled": True})
    places = _places(200)
    first = SpatialViewCells(cfg, PLATFORM)
    out1 = _drive(first, places, seed=1)
    assert not any(r["is_loop_closure"] for r in out1)  # 20 s: no place comes back
    state = first.state_dict()
    # the evidence a closure needs: sequence_m of travel at the typical speed, in frames of 0.1 s
    length = math.ceil(cfg.calibration.sequence_m / PLATFORM.speed_mps / 0.1)
    assert length == 20

    second = SpatialViewCells(cfg, PLATFORM)
    second.load_state_dict(state)
    second.new_session()
    out2 = _drive(second, places, seed=2)
    loops = [i for i, r in enumerate(out2) if r["is_loop_closure"]]
    # frame `length` is the first whose `length` frames before it all matched consistent places
    assert loops[0] == length and loops == list(range(length, len(places)))
    # each closure is onto its own place's template (place k made template k in the first session)
    assert all(out2[i]["id"] == out1[i]["id"] for i in loops)
    # the stored stamps moved back: they end a shortest loop and one frame before the session began
    stamps = np.asarray(second.interval_stamps)
    assert np.all(np.diff(stamps) > 0)
    assert stamps[199] == pytest.approx(-PLATFORM.min_revisit_s() - 0.1) and stamps[200] == 0.0

    # without the new session, its stamps restart below the stored ones: no stored place is older
    # than a shortest loop for its first 39.5 s, and nothing closes in these 20 s
    stale = SpatialViewCells(cfg, PLATFORM)
    stale.load_state_dict(state)
    assert not any(r["is_loop_closure"] for r in _drive(stale, places, seed=2))


def test_a_new_session_starts_an_interval_of_its_own_and_keeps_no_template_of_where_the_old_one_ended():
    """The old session ended at place 199; the new one starts at place 0. Its first frames are
    refused while their evidence gathers (sequence_m), and a refused frame that stands out may
    keep the current template (merge_revisits' hold): that must not be the old session's last
    template, or the pose cells read it as the robot being where the old session ended. A first
    view like the old session's last one opens an interval of its own too (the old interval's
    union is another time's)."""
    cfg = SpatialViewConfig(calibration={"enabled": True}, index_revisits=False, merge_revisits=True)
    places = _places(200)
    first = SpatialViewCells(cfg, PLATFORM)
    out1 = _drive(first, places, seed=1)
    last = out1[-1]["id"]
    state = first.state_dict()

    second = SpatialViewCells(cfg, PLATFORM)
    second.load_state_dict(state)
    second.new_session()
    out2 = _drive(second, places[:40], seed=2)
    assert all(r["id"] != last for r in out2)
    loops = [i for i, r in enumerate(out2) if r["is_loop_closure"]]
    assert loops and all(out2[i]["id"] == out1[i]["id"] for i in loops)  # and it does recognise them

    again = SpatialViewCells(cfg, PLATFORM)
    again.load_state_dict(state)
    again.new_session()
    n = again.n_intervals
    again.compute(places[-1], stamp=0.0)  # the very view the old session ended on
    assert again.n_intervals == n + 1 and again.current_template != last


# ---------------------------------------------------------------------------- pose cells
def _network() -> PoseCellNetwork:
    return PoseCellNetwork(pc_cell_x_size=1.0, exp_delta_pc_threshold=2.0)


def _step(pc: PoseCellNetwork, template: int, metres: float = 0.0) -> tuple[int, int, int, float]:
    pc.on_view_template(template)
    pc.on_odo(metres, 0.0, 1.0)
    return pc.get_action()


def test_the_first_stored_place_of_a_new_session_puts_the_packet_on_its_template():
    pc = _network()
    assert _step(pc, 0)[:3] == (CREATE_NODE, 0, 0)  # template 0, experience 0
    for _ in range(3):
        pc.on_odo(1.0, 0.0, 1.0)  # three cells on
    assert _step(pc, 1, 1.0)[:3] == (CREATE_NODE, 0, 1)  # template 1, experience 1, a fourth cell on
    pose0 = list(pc.templates[0][:3])
    state = pc.state_dict()

    pc.new_session()
    assert pc.current_exp == -1 and pc.lost
    # the new session's own first place: a new template where the stale packet is, no link to the old map
    action, src, dst, _ = _step(pc, 2, 1.0)
    assert (action, src, dst) == (CREATE_NODE, -1, 2) and (-1, 2) not in pc.links
    # a place of the earlier session: the packet starts again on its template's pose
    pc.on_view_template(0)
    assert not pc.lost and pc.best == pytest.approx(pose0)
    assert np.count_nonzero(pc.P) == 1
    pc.on_odo(0.0, 0.0, 1.0)
    assert pc.get_action()[:3] == (CREATE_EDGE, 2, 0)  # the new session's place links to experience 0

    # the old behaviour for contrast: the stale packet lies five cells from template 0, so the same
    # recognition makes a new experience there instead of returning to experience 0
    old = _network()
    old.load_state_dict(state)
    _step(old, 2, 1.0)
    assert _step(old, 0)[0] == CREATE_NODE


def test_the_gate_lets_the_first_recognition_of_a_new_session_through():
    gate = OdometryGate(radius_m=1.0, drift=0.0)
    gate.check(7)  # template 7 at the origin
    gate.on_odo(10.0, 0.0, 1.0)
    gate.check(8)
    assert not gate.check(7)  # 10 m from its place: refused
    gate.new_session()
    assert gate.check(7) and (gate.x, gate.y) == (0.0, 0.0)  # passes and re-anchors
    gate.on_odo(5.0, 0.0, 1.0)
    assert not gate.check(8)  # from then on the gate is as before


# ---------------------------------------------------------------------------- experience map
@pytest.mark.parametrize("relaxation", ["sweeps", "least_squares"])
def test_the_first_link_to_the_old_map_moves_the_new_sessions_part_rigidly_onto_it(relaxation):
    em = ExperienceMap(exp_initial_em_deg=0.0, exp_loops=0, relaxation=relaxation)
    em.on_odo(0.0, 0.0, 0.0)
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    em.on_odo(1.0, 0.0, 1.0)
    em.on_action(CREATE_NODE, 0, 1, 0.0)  # the old map: experience 0 at (0, 0), 1 at (1, 0)
    em.new_session()  # the new session starts from the old one's last pose, (1, 0) facing +x
    em.on_odo(0.5, 0.0, 1.0)
    em.on_action(CREATE_NODE, -1, 2, 0.0)  # its own part: (1.5, 0), linked to nothing
    em.on_odo(1.0, math.pi / 2, 1.0)
    em.on_action(CREATE_NODE, 2, 3, 0.0)  # a quarter turn, 1 m: (1.5, 1) facing +y
    assert em.n_links == 2 and em.part == [0, 0, 1, 1]
    # the robot, 0.5 m ahead of experience 3, is at experience 0: experience 3 lies 0.5 m behind
    # experience 0 facing as it does, (-0.5, 0, 0); experience 2, 1 m behind 3 before the quarter
    # turn, at (-1.5, 0) facing -pi/2; the old map stays
    em.on_odo(0.5, 0.0, 1.0)
    em.on_action(CREATE_EDGE, 3, 0, 0.0)
    nodes = em.node_poses()
    assert nodes[0] == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    assert nodes[1] == pytest.approx((1.0, 0.0, 0.0), abs=1e-12)
    assert nodes[3] == pytest.approx((-0.5, 0.0, 0.0), abs=1e-12)
    assert nodes[2] == pytest.approx((-1.5, 0.0, -math.pi / 2), abs=1e-12)
    assert em.part == [0, 0, 0, 0] and em.current == 0
    assert em.robot_pose() == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    # a stored map's parts follow from its links
    other = ExperienceMap(exp_initial_em_deg=0.0, exp_loops=0, relaxation=relaxation)
    other.load_state_dict(em.state_dict())
    assert other.part == [0, 0, 0, 0]


# ---------------------------------------------------------------------------- the default, end to end
def _neoslam(*args: str) -> None:
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "neoslam_stream.cli", *args], capture_output=True, text=True,
                       timeout=900)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]


@pytest.mark.slow
@pytest.mark.zenoh
def test_the_default_on_yesterdays_map_recognises_its_places_and_stays_on_it(tmp_path):
    """The shipped default: 600 frames of the default route (no revisit in them), its map exported,
    then a second session of the route's first 300 frames on that map. Every frame of the second
    session shows a stored place, so closures begin as soon as their evidence can (sequence_m of
    travel), and frame f of the second session lies where frame f of the first did (the same true
    pose) on the map, within the map's own resolution (one experience spacing)."""
    from neoslam_stream.config import load_config
    from neoslam_stream.tum import read_tum

    first, second, site = tmp_path / "first", tmp_path / "second", tmp_path / "site.neoslam"
    _neoslam("run", "--max-frames", "600", "--no-live", "--out", str(first))
    _neoslam("map", "export", str(first), "--out", str(site))
    _neoslam("run", "--map", str(site), "--max-frames", "300", "--no-live", "--out", str(second))

    rows = np.loadtxt(second / "templates.csv", delimiter=",", skiprows=1).reshape(-1, 6)
    loops = np.flatnonzero(rows[:, 3] == 1)
    cfg = load_config("default")
    evidence = math.ceil(cfg.spatial_view.calibration.sequence_m / cfg.platform.speed_mps / 0.1)  # 20 frames
    assert evidence <= loops[0] <= 2 * evidence, loops[:5]
    assert len(loops) >= 0.9 * (300 - loops[0])  # and then nearly every frame
    # the poses of both sessions on the final maps, frame by frame
    a, b = read_tum(first / "trajectory_map.tum"), read_tum(second / "trajectory_map.tum")
    assert len(b) == 300
    apart = np.hypot(*(a[:300, 1:3] - b[:, 1:3]).T)
    spacing = cfg.pose_cells.exp_delta_pc_threshold * cfg.pose_cells.pc_cell_x_size  # 0.6 m
    assert apart.mean() < spacing and apart.max() < 2 * spacing, (apart.mean(), apart.max())
    # one map: the second session's experiences are linked to the first's
    mp = json.loads((second / "map.json").read_text())
    ids = {n["id"]: i for i, n in enumerate(mp["nodes"])}
    links = np.array([[ids[lk["from"]], ids[lk["to"]]] for lk in mp["links"]]).reshape(-1, 2)
    adjacency = sp.csr_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(len(ids), len(ids)))
    assert connected_components(adjacency, directed=False)[0] == 1


def test_the_local_view_also_recognises_the_stored_places_of_a_new_session():
    from neoslam_stream.algorithms.frontend import LocalViewFrontEnd, LocalViewFrontEndConfig

    cfg = LocalViewFrontEndConfig(calibration={"enabled": True})
    rng = np.random.default_rng(0)
    views = [rng.integers(0, 256, (60, 80), dtype=np.uint8) for _ in range(150)]

    def drive(lv: LocalViewFrontEnd, seed: int) -> list[dict]:
        noise = np.random.default_rng(seed)
        return [lv.template(np.clip(v + noise.integers(-3, 4, v.shape), 0, 255).astype(np.uint8), 0.1 * i)
                for i, v in enumerate(views)]

    first = LocalViewFrontEnd(cfg, PLATFORM)
    out1 = drive(first, 1)
    assert not any(t["is_loop_closure"] for t in out1)
    second = LocalViewFrontEnd(cfg, PLATFORM)
    second.load_state_dict(first.state_dict())
    second.new_session()
    out2 = drive(second, 2)
    loops = [i for i, t in enumerate(out2) if t["is_loop_closure"]]
    length = math.ceil(cfg.calibration.sequence_m / PLATFORM.speed_mps / 0.1)
    assert loops and loops[0] == length and all(out2[i]["id"] == out1[i]["id"] for i in loops)
