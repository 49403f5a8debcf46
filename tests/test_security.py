"""Safe defaults: loopback-only endpoints, no scouting, size limits before decoding, no code from
received data, validated config paths. See the README section "Security"."""

from __future__ import annotations

import json
import re
from pathlib import Path

import msgpack
import pytest

from neoslam_stream.config import ConfigError, load_config
from neoslam_stream.runtime.bus import make_config
from neoslam_stream.runtime.messages import MAX_MESSAGE_BYTES, MessageError, decode

PKG = Path(__file__).resolve().parents[1] / "neoslam_stream"


def test_a_run_listens_on_loopback_only_by_default(tmp_path):
    from neoslam_stream.nodes.pipelines import build_plan
    from neoslam_stream.runtime.topology import Supervisor

    cfg = load_config("default", {"run": {"live": False}})
    sup = Supervisor(cfg, build_plan(cfg), tmp_path / "run")
    layout = sup.layout
    assert layout.endpoints and all(re.fullmatch(r"tcp/127\.0\.0\.1:\d+", e) for e in layout.endpoints.values())
    for name in layout.order[1:-1]:
        listen, connect = layout.links(name)
        assert all(e.startswith("tcp/127.0.0.1:") for e in listen + connect)


def test_zenoh_config_has_scouting_off_and_explicit_endpoints():
    conf = make_config(["tcp/127.0.0.1:7447"], [])
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    # never zenoh's peer default tcp/[::]:0 (every interface)
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]


def test_size_limit_is_checked_before_decoding():
    with pytest.raises(MessageError, match="MAX_MESSAGE_BYTES"):
        decode(bytes(MAX_MESSAGE_BYTES + 1))
    # a tiny payload claiming a 4 GB binary: refused, nothing of that size is allocated
    claim = b"\x81\xa4data\xc6\xff\xff\xff\xff"
    with pytest.raises(MessageError):
        decode(claim)
    with pytest.raises(MessageError):
        decode(msgpack.packb({"v": 1, "type": "image", "frame": 0, "stamp": 0.0, "trace": [],
                              "data": {"image": {"__ndarray__": "not an ext type"}}}))


def test_no_code_is_run_from_received_or_stored_data():
    """No pickle, eval or exec anywhere received bytes or files are read: msgpack with one
    registered extension type (arrays), YAML through safe_load, checkpoints in msgpack."""
    offenders = []
    for path in PKG.rglob("*.py"):
        text = path.read_text()
        for pattern in (r"\bpickle\.loads?\(", r"(?<![.\w])eval\(", r"(?<![.\w])exec\(", r"yaml\.load\(", r"torch\.load\((?![^)]*weights_only=True)"):
            if re.search(pattern, text):
                offenders.append(f"{path.name}: {pattern}")
    assert offenders == []


def test_config_paths_are_validated_with_clear_errors(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.yaml")
    from neoslam_stream.algorithms.features import VisualFeatureExtractor

    with pytest.raises(FileNotFoundError, match="nowhere.pth"):
        VisualFeatureExtractor(backbone="alexnet", weights_path=str(tmp_path / "nowhere.pth"))
    from neoslam_stream.algorithms.projector import BinaryProjector

    bad = tmp_path / "randomMatrix.bin"
    bad.write_bytes(b"\x00" * 1000)
    with pytest.raises(ValueError, match="bytes"):
        BinaryProjector(matrix_path=str(bad))


def test_a_zenoh_config_file_adds_settings_but_never_reopens_scouting(tmp_path, monkeypatch):
    from neoslam_stream.runtime.bus import ZENOH_CONFIG_ENV

    f = tmp_path / "zenoh.json5"
    f.write_text('{ metadata: { name: "robot1" }, scouting: { multicast: { enabled: true } } }')
    monkeypatch.setenv(ZENOH_CONFIG_ENV, str(f))
    conf = make_config(["tcp/127.0.0.1:7447"], [])
    assert json.loads(conf.get_json("metadata"))["name"] == "robot1"  # the file's settings apply
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False  # ours win
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(None, {"bus": {"zenoh_config": str(tmp_path / "missing.json5")}})
