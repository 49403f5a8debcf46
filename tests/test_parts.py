"""One run over several hosts (``neoslam run --stages ...``): here two supervisors on one machine
that reach each other only through a zenoh router on loopback."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from runhelpers import light_config

from neoslam_stream.config import load_config
from neoslam_stream.nodes.pipelines import build_plan
from neoslam_stream.runtime.ports import free_port
from neoslam_stream.runtime.share import ShareSupervisor, check_selection, parse_stages
from neoslam_stream.runtime.topology import CONTROL_TOKEN_ENV, RunError, group_workers

FRAMES = 30
TINY = light_config("lossless", {"kind": "synthetic", "params": {"seed": 0, "frames": FRAMES}})


def test_stage_lists_are_parsed_and_checked():
    assert parse_stages("A, B") == ["A", "B"]
    assert parse_stages("rest") == ["rest"]
    assert parse_stages("A,B,source") == ["A", "B", "source"]  # the source on this host too
    for bad in ("", "rest,A"):
        with pytest.raises(ValueError):
            parse_stages(bad)
    groups = group_workers(build_plan(load_config("default")), "pipeline")
    assert check_selection(groups, ["B", "A"]) == ["A", "B"]  # the plan's order
    assert check_selection(groups, ["A", "B", "source"]) == ["A", "B"]  # the source is no worker
    with pytest.raises(RunError, match="unknown stage"):
        check_selection(groups, ["A", "Z"])
    with pytest.raises(RunError, match="experience_map"):  # the recorder is no process of its own
        check_selection(groups, ["recorder"])


def test_a_share_needs_a_run_id_and_the_pipeline_topology(tmp_path):
    cfg = load_config("default", {"run": {"stages": ["A"]}})
    with pytest.raises(RunError, match="--run-id"):
        ShareSupervisor(cfg, build_plan(cfg), tmp_path / "a")
    cfg = load_config("default", {"run": {"stages": ["A"], "run_id": "x1", "topology": "monolithic"}})
    with pytest.raises(RunError, match="pipeline topology"):
        ShareSupervisor(cfg, build_plan(cfg), tmp_path / "b")


def test_a_share_needs_the_runs_control_secret(tmp_path, monkeypatch):
    # the source's host stops the other hosts' workers with control messages, which workers obey
    # only with the run's secret: without a shared one the split run could never end cleanly
    monkeypatch.delenv(CONTROL_TOKEN_ENV, raising=False)
    cfg = load_config("default", {"run": {"stages": ["A"], "run_id": "x3"}})
    with pytest.raises(RunError, match=CONTROL_TOKEN_ENV):
        ShareSupervisor(cfg, build_plan(cfg), tmp_path / "a")
    monkeypatch.setenv(CONTROL_TOKEN_ENV, "s3cret")
    assert ShareSupervisor(cfg, build_plan(cfg), tmp_path / "b").control_token == "s3cret"


def test_only_the_supervisors_router_links_to_other_hosts(tmp_path, monkeypatch):
    monkeypatch.setenv(CONTROL_TOKEN_ENV, "s3cret")
    # bus.connect names the router between hosts: the supervisor's session connects to it, no
    # other process does (zenoh routes between peers of linked routers, not between peers that
    # merely share a router), and no process links to another host's processes
    cfg = load_config("default", {"run": {"stages": ["A", "B"], "run_id": "x2"},
                                  "bus": {"connect": ["tcp/127.0.0.1:7"]}})
    sup = ShareSupervisor(cfg, build_plan(cfg), tmp_path / "a")
    layout = sup.layout
    layout.order = ["supervisor", *layout.hosted]  # as _select_hosted sets it for a share without the source
    for w in layout.hosted:
        spec = layout.worker_spec(w)
        assert "tcp/127.0.0.1:7" not in spec.connect
        assert set(spec.connect) <= {layout.endpoints[n] for n in layout.order}
        assert spec.expected_peers == layout.order.index(w)


def test_the_primarys_saved_figures_carry_a_format_version(tmp_path, monkeypatch):
    # what a resumed primary reads back (parts_state.json): the figures round-trip; a file of
    # another version, or without one, is refused with one line naming it and both versions
    from types import SimpleNamespace

    from neoslam_stream.runtime.checkpoint import StateFormatError
    from neoslam_stream.runtime.share_recovery import STATE_FILE, STATE_VERSION

    monkeypatch.setenv(CONTROL_TOKEN_ENV, "s3cret")
    cfg = load_config("default", {"run": {"stages": ["C", "D"], "run_id": "x4"}})
    sup = ShareSupervisor(cfg, build_plan(cfg), tmp_path / "a")
    sup.collector.add({"stage": "C", "pid": 1, "received": 4, "processed": 4})
    sup.final.frames.add(3)
    sup.children.restart_events.append({"worker": "C", "exit_code": -9})
    sup.recovery.link = SimpleNamespace(all_outages=lambda: [{"host": "A,B", "start_wall": 1.0}])
    sup.recovery.persist()
    path = tmp_path / "a" / STATE_FILE
    saved = json.loads(path.read_text())
    assert saved["format"] == "neoslam-share-state" and saved["version"] == STATE_VERSION
    again = ShareSupervisor(cfg, build_plan(cfg), tmp_path / "b")
    again.recovery.restore(path)
    assert again.collector.raw["C"]["processed"] == 4 and again.final.frames == {3}
    assert again.children.restart_events == [{"worker": "C", "exit_code": -9}]
    assert again.recovery.outages() == [{"host": "A,B", "start_wall": 1.0}]
    for found, has in ((None, "no format version"), (STATE_VERSION + 1, f"format version {STATE_VERSION + 1}")):
        other = dict(saved)
        if found is None:
            del other["format"], other["version"]
        else:
            other["version"] = found
        path.write_text(json.dumps(other))
        with pytest.raises(StateFormatError) as err:
            again.recovery.restore(path)
        assert str(err.value) == (f"{path} has {has}; this build reads version {STATE_VERSION} "
                                  f"(it was written by another version of neoslam)")


def _start(tmp_path: Path, name: str, *args: str) -> subprocess.Popen:
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(TINY))
    return subprocess.Popen([sys.executable, "-m", "neoslam_stream.cli", "run", "-c", str(cfg),
                             "--out", str(tmp_path / name), *args],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, CONTROL_TOKEN_ENV: "the-hosts-shared-secret"})


@pytest.mark.zenoh
@pytest.mark.slow
def test_two_hosts_through_a_router_make_one_lossless_run(tmp_path):
    port = free_port()
    router = subprocess.Popen([sys.executable, "-m", "neoslam_stream.cli", "router", "--listen",
                               f"tcp/127.0.0.1:{port}", "--duration", "500"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    link = ["--run-id", "twohosts", "--connect", f"tcp/127.0.0.1:{port}"]
    try:
        time.sleep(1.0)
        front = _start(tmp_path, "front", "--stages", "A,B", *link)
        back = _start(tmp_path, "back", "--stages", "rest", *link)
        out_back, _ = back.communicate(timeout=500)
        out_front, _ = front.communicate(timeout=120)
    finally:
        router.terminate()
        router.wait(10)
        for p in (locals().get("front"), locals().get("back")):
            if p is not None and p.poll() is None:
                p.kill()
    assert back.returncode == 0, out_back[-3000:]
    assert front.returncode == 0, out_front[-3000:]
    # the front host ran A and B only; the back end host ran the rest, the source and the monitor
    share = json.loads((tmp_path / "front" / "part.json").read_text())
    assert share["part"] == ["A", "B"] and share["restarts"] == {}
    assert not (tmp_path / "front" / "report.json").exists()
    report = json.loads((tmp_path / "back" / "report.json").read_text())
    assert report["hosted_here"] == ["C", "D", "pose_cells", "experience_map"]
    # the monitor saw every stage, wherever it ran, and nothing was lost
    for stage in ("A", "B", "C", "D", "pose_cells", "experience_map", "recorder"):
        assert not report["stages"][stage].get("missing"), stage
    for stage in ("A", "B", "C", "D", "experience_map"):
        assert report["stages"][stage]["processed"] == FRAMES, stage
    assert report["frames_in"] == report["frames_out"] == FRAMES and report["loss"] == 0.0
    # every frame has its template and its pose
    with (tmp_path / "back" / "templates.csv").open() as f:
        assert [int(r["frame"]) for r in csv.DictReader(f)] == list(range(FRAMES))
    rows = [r for r in (tmp_path / "back" / "trajectory.tum").read_text().splitlines() if r.strip()]
    assert len(rows) == FRAMES


# --------------------------------------------------------------------------- TLS and access control
ROUTER_JSON5 = """{
  transport: { link: { tls: {
    listen_private_key: "%(d)s/router.key", listen_certificate: "%(d)s/router.crt",
    root_ca_certificate: "%(d)s/ca.crt", enable_mtls: true } } },
  access_control: { enabled: true, default_permission: "deny",
    rules: [ { id: "neoslam", permission: "allow", flows: ["ingress", "egress"],
               messages: ["put", "declare_subscriber", "liveliness_token", "liveliness_query",
                          "declare_liveliness_subscriber", "reply"],
               key_exprs: ["neoslam/**"] } ],
    subjects: [ { id: "hosts", cert_common_names: ["gpu-box"] } ],
    policies: [ { rules: ["neoslam"], subjects: ["hosts"] } ] },
}"""
HOST_JSON5 = """{ transport: { link: { tls: { root_ca_certificate: "%(d)s/ca.crt", enable_mtls: true,
    connect_private_key: "%(d)s/%(n)s.key", connect_certificate: "%(d)s/%(n)s.crt" } } } }"""


def _certificates(d: Path) -> None:
    """A CA, and certificates for the router (localhost) and two hosts, made with openssl."""
    def ossl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True)

    ossl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.crt",
         "-days", "2", "-subj", "/CN=neoslam-test-ca")
    for name, cn in (("router", "router"), ("gpu-box", "gpu-box"), ("stranger", "stranger")):
        (d / f"{name}.ext").write_text("subjectAltName=DNS:localhost\nextendedKeyUsage=serverAuth,clientAuth\n")
        ossl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key", "-out", f"{name}.csr",
             "-subj", f"/CN={cn}")
        ossl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.crt", "-CAkey", "ca.key", "-CAcreateserial",
             "-out", f"{name}.crt", "-days", "2", "-extfile", f"{name}.ext")


@pytest.mark.zenoh
@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl to make test certificates")
def test_router_with_tls_and_access_control_as_documented(tmp_path, monkeypatch):
    from neoslam_stream.runtime.bus import ZENOH_CONFIG_ENV, open_session

    _certificates(tmp_path)
    (tmp_path / "router.json5").write_text(ROUTER_JSON5 % {"d": tmp_path})
    for n in ("gpu-box", "stranger"):
        (tmp_path / f"{n}.json5").write_text(HOST_JSON5 % {"d": tmp_path, "n": n})
    (tmp_path / "nocert.json5").write_text(
        '{ transport: { link: { tls: { root_ca_certificate: "' + f'{tmp_path}/ca.crt' + '" } } } }')
    ep = f"tls/localhost:{free_port()}"
    router = subprocess.Popen([sys.executable, "-m", "neoslam_stream.cli", "router", "--listen", ep,
                               "--zenoh-config", str(tmp_path / "router.json5"), "--duration", "60"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    sessions = []
    try:
        def client(name: str):
            monkeypatch.setenv(ZENOH_CONFIG_ENV, str(tmp_path / f"{name}.json5"))
            deadline = time.monotonic() + 20
            while True:  # the router may still be starting
                try:
                    s = open_session([], [ep], mode="client")
                    sessions.append(s)
                    return s
                except Exception:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.3)

        pub, sub = client("gpu-box"), client("gpu-box")
        got: list[str] = []
        for key in ("neoslam/r1/image", "other/r1/image"):
            sub.declare_subscriber(key, lambda s: got.append(str(s.key_expr)))
        time.sleep(1.0)
        for key in ("neoslam/r1/image", "other/r1/image"):
            pub.put(key, b"x")
        deadline = time.monotonic() + 5
        while not got and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(0.5)
        assert got == ["neoslam/r1/image"]  # the access-control rule passes neoslam/** only
        # a certificate of the CA but a common name the policy does not name: connected, denied
        stranger = client("stranger")
        stranger.put("neoslam/r1/image", b"y")
        time.sleep(1.0)
        assert got == ["neoslam/r1/image"]
        # no client certificate: mutual TLS refuses the link
        monkeypatch.setenv(ZENOH_CONFIG_ENV, str(tmp_path / "nocert.json5"))
        with pytest.raises(Exception, match="connect"):
            sessions.append(open_session([], [ep], mode="client"))
    finally:
        for s in sessions:
            s.close()
        router.terminate()
        router.wait(10)
