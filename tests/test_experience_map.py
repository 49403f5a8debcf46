"""Experience map: dead reckoning, links and relaxation of a loop with a known error."""

import math

import numpy as np
import pytest

from neoslam_stream.algorithms.ratslam.experience_map import ExperienceMap
from neoslam_stream.algorithms.ratslam.map_poses import poses_on_map
from neoslam_stream.algorithms.ratslam.pose_cells import CREATE_EDGE, CREATE_NODE


def test_dead_reckoning_places_nodes():
    em = ExperienceMap(exp_initial_em_deg=0, exp_loops=0)
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    em.on_odo(1.0, 0.0, 2.0)  # 2 m along +x
    em.on_action(CREATE_NODE, 0, 1, 0.0)
    assert (em.x[1], em.y[1]) == pytest.approx((2.0, 0.0))
    em.on_odo(0.0, math.pi / 2, 1.0)
    em.on_odo(1.0, 0.0, 1.0)
    em.on_action(CREATE_NODE, 1, 2, 0.0)
    assert (em.x[2], em.y[2]) == pytest.approx((2.0, 1.0))
    assert em.th[2] == pytest.approx(math.pi / 2)


def test_relaxation_closes_a_square_loop_with_known_error():
    em = ExperienceMap(exp_initial_em_deg=0, exp_loops=200)
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    # a 1 m square driven with 10 % too long odometry on the last side
    sides = [1.0, 1.0, 1.0, 1.1]
    for k, d in enumerate(sides[:3]):
        em.on_odo(d, 0.0, 1.0)
        em.on_action(CREATE_NODE, k, k + 1, 0.0)
        em.on_odo(0.0, math.pi / 2, 1.0)
    em.on_odo(sides[3], 0.0, 1.0)
    em.on_odo(0.0, math.pi / 2, 1.0)  # face the way the loop started, as a real revisit does
    before = math.hypot(em.robot_pose()[0], em.robot_pose()[1])
    assert before == pytest.approx(0.1, abs=1e-9)  # the dead-reckoned gap at the loop's end
    em.on_action(CREATE_EDGE, 3, 0, 0.0)  # recognised the start: close the loop
    assert len(em.links) == 4

    def residual(link):  # where the link says its end node is, versus where it is
        a, b, d, heading, _facing, _t = link
        lx = em.x[a] + d * math.cos(em.th[a] + heading)
        ly = em.y[a] + d * math.sin(em.th[a] + heading)
        return math.hypot(em.x[b] - lx, em.y[b] - ly)

    res = [residual(lk) for lk in em.links]
    # before relaxation the whole 0.1 m sat on the closing link; a loop of 4 links shares it,
    # 0.1 / 4 = 0.025 m each in the least-squares sense: no link may keep more than half of it
    assert max(res) < 0.05
    assert sum(res) == pytest.approx(0.1, abs=0.03)


def test_duplicate_links_not_created():
    em = ExperienceMap()
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    em.on_odo(1, 0, 1)
    em.on_action(CREATE_NODE, 0, 1, 0.0)
    em.on_action(CREATE_EDGE, 1, 0, 0.0)  # 1 -> 0 exists as 0 -> 1
    assert len(em.links) == 1


def test_unknown_experience_in_a_link_rejected():
    em = ExperienceMap()
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    with pytest.raises(ValueError):
        em.create_link(0, 7, 0.0)
    with pytest.raises(ValueError):
        em.on_action(9, 0, 0, 0.0)  # not an action


def test_lost_and_repeated_actions_are_repaired():
    """After a lost CREATE_NODE the next actions name an experience the map never saw."""
    em = ExperienceMap(exp_initial_em_deg=0, exp_loops=0)
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    em.on_odo(1.0, 0.0, 1.0)
    # CREATE_NODE 0 -> 1 was lost; 1 -> 2 arrives after another metre
    em.on_odo(1.0, 0.0, 1.0)
    em.on_action(CREATE_NODE, 1, 2, 0.0)
    assert em.n_experiences == 2 and em.current == 2
    assert (em.x[1], em.y[1]) == pytest.approx((2.0, 0.0))  # where dead reckoning put it
    em.on_odo(1.0, 0.0, 1.0)
    em.on_action(CREATE_EDGE, 2, 5, 0.0)  # an edge to an id never created: created here
    assert em.current == 5 and (em.x[2], em.y[2]) == pytest.approx((3.0, 0.0))
    em.on_odo(-3.0, 0.0, 1.0)
    em.on_action(CREATE_NODE, 5, 0, 0.0)  # a repeated CREATE_NODE of a known id: a link to it
    assert em.n_experiences == 3 and em.current == 0
    assert [(a, b) for a, b, *_ in em.links] == [(0, 2), (2, 5), (5, 0)]
    assert em.repaired_actions == 2
    assert [n["id"] for n in em.export()["nodes"]] == [0, 2, 5]


def test_link_starts_at_current_experience_in_fixed_mode_and_at_src_in_compat():
    for compat, expected in ((False, (4, 2)), (True, (0, 2))):
        em = ExperienceMap(exp_loops=0, openratslam_compat=compat)
        for i in range(5):  # a chain 0-1-2-3-4, the map at 4
            em.on_odo(1.0, 0.0, 1.0)
            em.on_action(CREATE_NODE, max(i - 1, 0), i, 0.0)
        n_links = len(em.links)
        em.on_action(CREATE_EDGE, 0, 2, 0.0)  # src 0 is stale (actions were lost): the map is at 4
        assert len(em.links) == n_links + 1 and em.links[-1][:2] == expected


def test_state_round_trip():
    em = ExperienceMap(exp_loops=3)
    for i in range(4):
        em.on_odo(1.0, 0.3, 1.0)
        em.on_action(CREATE_NODE, max(i - 1, 0), i, 0.0, stamp=float(i))
    em.on_action(CREATE_EDGE, 3, 0, 0.0)
    twin = ExperienceMap(exp_loops=3)
    twin.load_state_dict(em.state_dict())
    for m in (em, twin):
        m.on_odo(0.5, -0.1, 1.0)
        m.on_action(CREATE_NODE, 0, 4, 0.0)
    assert twin.export() == em.export()


def _action(frame, action, src, dst, vtrans=1.0, vrot=0.0, dt=1.0):
    from neoslam_stream.runtime.messages import Message

    return Message("pose_cells/action", frame, float(frame),
                   {"action": action, "src_id": src, "dst_id": dst, "relative_rad": 0.0,
                    "vtrans": vtrans, "vrot": vrot, "dt": dt})


def test_node_publishes_a_pose_per_action_and_the_map_at_flush(tmp_path):
    import json

    from neoslam_stream.nodes.ratslam import ExperienceMapNode
    from neoslam_stream.nodes.recorder import RecorderNode
    from neoslam_stream.runtime.messages import decode, encode

    st = ExperienceMapNode(exp_initial_em_deg=0, exp_loops=0)
    rec = RecorderNode()
    rec.run_dir = str(tmp_path)
    msgs = [_action(0, CREATE_NODE, 0, 0), _action(1, 0, 0, 0), _action(2, CREATE_NODE, 0, 1),
            _action(3, CREATE_NODE, 1, 7)]  # id 7: a CREATE_NODE with a skipped id is fine
    poses = []
    for m in msgs:
        (topic, pose), = st.process("pose_cells/action", m)
        rec.process(topic, pose)
        poses.append(pose)
    # pose = current experience + dead reckoning since: 1 m along +x per message
    assert [p["pose"][0] for p in poses] == pytest.approx([1.0, 2.0, 3.0, 4.0])
    assert [p["exp_id"] for p in poses] == [0, 0, 1, 7]
    out = st.flush()
    assert [t for t, _ in out] == ["experience_map/map"]
    m = decode(encode(out[0][1]))  # the whole map crosses the wire, its export included
    np.testing.assert_allclose(m["nodes"][:, :3], [[0, 1, 0], [1, 3, 0], [7, 4, 0]])
    assert m["links"].tolist() == [[0, 1], [1, 7]]
    rec.process(out[0][0], m)
    rec.flush()
    saved = json.loads((tmp_path / "map.json").read_text())
    assert [n["id"] for n in saved["nodes"]] == [0, 1, 7] and len(saved["links"]) == 2
    tum = (tmp_path / "trajectory.tum").read_text().splitlines()
    assert [float(line.split()[1]) for line in tum] == pytest.approx([1.0, 2.0, 3.0, 4.0])


def test_local_pose_re_expressed_on_the_unchanged_map_is_the_robot_pose():
    em = ExperienceMap(exp_initial_em_deg=30, exp_loops=0)
    assert em.local_pose()[0] == -1  # before the first experience: the absolute pose
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    em.on_odo(1.0, 0.4, 1.5)
    em.on_action(CREATE_NODE, 0, 1, 0.0)
    em.on_odo(0.7, -0.9, 1.0)
    em.on_odo(0.2, 0.3, 2.0)
    exp_id, *local = em.local_pose()
    nodes = em.node_poses()  # every experience's pose now, as the exported map gives it
    assert nodes == {n["id"]: (n["x"], n["y"], n["theta"]) for n in em.export()["nodes"]} and len(nodes) == 2
    (x, y, th), = poses_on_map(nodes, np.array([exp_id]), np.array([local]))
    assert (x, y, th) == pytest.approx(em.robot_pose(), abs=1e-12)


def test_poses_on_map_follow_their_experience_when_relaxation_moves_it():
    # by hand: the robot stood 1 m ahead and 0.5 m to the left of experience 4 (heading 0), facing
    # 0.2 rad more than it; the final map moved experience 4 to (10, 5) and turned it to 90 deg, so
    # ahead is +y and left is -x: (10 - 0.5, 5 + 1), heading pi/2 + 0.2
    nodes = {4: (10.0, 5.0, math.pi / 2)}
    out = poses_on_map(nodes, np.array([4, -1, 9]), np.array([[1.0, 0.5, 0.2], [3.0, 4.0, 0.1], [1.0, 2.0, 0.3]]))
    np.testing.assert_allclose(out[0], [9.5, 6.0, math.pi / 2 + 0.2], atol=1e-12)
    # no experience yet (-1), or one the map does not hold: the pose stays as it was
    np.testing.assert_allclose(out[1:], [[3.0, 4.0, 0.1], [1.0, 2.0, 0.3]])


def test_the_recorder_writes_the_trajectory_on_the_final_map(tmp_path):
    from neoslam_stream.nodes.ratslam import ExperienceMapNode
    from neoslam_stream.nodes.recorder import RecorderNode
    from neoslam_stream.runtime.messages import decode, encode
    from neoslam_stream.tum import read_tum

    st = ExperienceMapNode(exp_initial_em_deg=0, exp_loops=0)
    rec = RecorderNode()
    rec.run_dir = str(tmp_path)
    for m in (_action(0, CREATE_NODE, 0, 0), _action(1, 0, 0, 0), _action(2, CREATE_NODE, 0, 1), _action(3, 0, 1, 1)):
        (topic, pose), = st.process("pose_cells/action", m)
        rec.process(topic, decode(encode(pose)))  # the offsets cross the wire
    (topic, m), = st.flush()
    # as if relaxation had moved experience 1 (at x = 3) to (3, 2) and turned it by 90 degrees:
    # frame 2 stood on it, frame 3 1 m ahead of it, i.e. now 1 m along +y
    export = m["export"]
    export["nodes"][1].update(x=3.0, y=2.0, theta=math.pi / 2)
    rec.process(topic, m)
    rec.flush()
    on_map = read_tum(tmp_path / "trajectory_map.tum")
    online = read_tum(tmp_path / "trajectory.tum")
    np.testing.assert_allclose(on_map[:, 0], online[:, 0])  # the same stamps
    np.testing.assert_allclose(on_map[:, 1:3], [[1, 0], [2, 0], [3, 2], [3, 3]], atol=1e-9)
    # a recorder restored from a checkpoint file keeps the offsets
    from neoslam_stream.runtime.checkpoint import load_state_file, save_state_file

    save_state_file(tmp_path / "rec.state", rec.state_dict())
    again = RecorderNode()
    again.load_state_dict(load_state_file(tmp_path / "rec.state"))
    again.folder.on_map(export)
    assert again.folder.trajectory_on_map() == (tmp_path / "trajectory_map.tum").read_text()


def test_actions_without_odometry_are_refused_by_the_topic_schema():
    from neoslam_stream.nodes.topics import POSE_CELL_ACTION
    from neoslam_stream.runtime.messages import Message, MessageError, encode, register_topics

    assert {"vtrans", "vrot", "dt"} <= set(POSE_CELL_ACTION.schema)
    register_topics([POSE_CELL_ACTION])
    bad = Message("pose_cells/action", 0, 0.0, {"action": 1, "src_id": 0, "dst_id": 0})
    with pytest.raises(MessageError, match="vtrans"):
        encode(bad)
    nan = Message("pose_cells/action", 0, 0.0, {"action": 1, "src_id": 0, "dst_id": 0, "vtrans": float("nan"),
                                                "vrot": 0.0, "dt": 1.0})
    with pytest.raises(MessageError, match="not finite"):
        encode(nan)


def test_a_viewed_node_publishes_its_map_now_and_then_and_the_recorder_keeps_the_final_one(tmp_path):
    """``map_period_s`` (a run served to Foxglove): the map's nodes and links (no export) at most that
    often in source time and only when the map changed; the recorder writes map.json from the final."""
    import json

    from neoslam_stream.nodes.ratslam import ExperienceMapNode
    from neoslam_stream.nodes.recorder import RecorderNode
    from neoslam_stream.runtime.messages import decode, encode

    st = ExperienceMapNode(map_period_s=2.0, exp_initial_em_deg=0, exp_loops=0)
    rec = RecorderNode()
    rec.run_dir = str(tmp_path)
    maps = []
    steps = [(0, CREATE_NODE, 0, 0), (1, 0, 0, 0), (2, 0, 0, 0), (3, CREATE_NODE, 0, 1), (4, 0, 1, 1),
             (5, CREATE_NODE, 1, 2), (6, CREATE_EDGE, 2, 0)]
    for args in steps:
        for topic, msg in st.process("pose_cells/action", _action(*args)):
            rec.process(topic, decode(encode(msg)))
            if topic == "experience_map/map":
                maps.append(decode(encode(msg)))
    # at stamp 0 (a first experience), 3 (a second, 3 s later), 5 (a third: 2 s later), 6 is too soon
    assert [m.stamp for m in maps] == [0.0, 3.0, 5.0]
    assert all("export" not in m.data for m in maps)
    assert [len(m["nodes"]) for m in maps] == [1, 2, 3] and maps[-1]["links"].tolist() == [[0, 1], [1, 2]]
    (topic, final), = st.flush()
    rec.process(topic, decode(encode(final)))
    rec.flush()
    saved = json.loads((tmp_path / "map.json").read_text())
    assert len(saved["links"]) == 3  # the final map's, the loop link included
    plain = ExperienceMapNode(exp_initial_em_deg=0, exp_loops=0)  # by default, no map before the end
    assert [t for t, _ in plain.process("pose_cells/action", _action(0, CREATE_NODE, 0, 0))] == ["experience_map/pose"]
