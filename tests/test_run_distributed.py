"""The distributed service as real processes on loopback: router, replay, learner, scheduler,
actors. Every wait polls with a deadline; every process is stopped at the end."""

from __future__ import annotations

import json
import urllib.error
import urllib.request

import pytest
from conftest import wait_for

from curlnav.bus.transport import reliable_publisher
from curlnav.config import resolve_config
from curlnav.proto.topology import Topology
from curlnav.run.launch import LocalCluster, http_json

pytestmark = [pytest.mark.net, pytest.mark.slow]

CURRICULUM = """
name: tiny
stages:
  - name: S1
    worlds: [open-room]
    advance: {success_rate: 0.0, window: 4}
  - name: S2
    worlds: [door-corridor]
    substeps: [through-door]
    advance: {success_rate: 0.5, window: 10, source: evaluation}
  - name: S3
    worlds: [open-room]
"""


def metric(url: str, name: str) -> float:
    text = urllib.request.urlopen(url, timeout=5).read().decode()
    return sum(float(line.split()[-1]) for line in text.splitlines() if line.startswith(name))


@pytest.fixture
def cluster(tmp_path):
    (tmp_path / "tiny.yaml").write_text(CURRICULUM)
    experiment = resolve_config(overrides=[f"curriculum.file={tmp_path / 'tiny.yaml'}", "replay.min_size=200",
                                           "replay.samples_per_insert=8", "d4pg.batch_size=128"])
    c = LocalCluster(tmp_path / "run", experiment, actors=2, run="itest", admin_token="secret",
                     extra={"learner": ["--publish-every", "5", "--export-every-s", "5"]})
    c.start()
    try:
        yield c
    finally:
        c.stop()
        assert not c.processes


def test_the_service_trains_advances_tracks_actors_and_survives_bad_input(cluster):
    status = cluster.status
    # transitions reach the replay, the learner's version rises, both actors report episodes
    s = wait_for("episodes from both actors and learner version >= 2", lambda: (
        (st := status()) and st["replay"]["size"] and (st["learner"]["version"] or 0) >= 2
        and all(a.get("episodes", 0) > 0 for a in st["live_actors"].values()) and len(st["live_actors"]) == 2 and st),
        timeout=300)
    assert s["replay"]["size"] > 0 and set(s["live_actors"]) == {"actor-0", "actor-1"}
    # actors pick up new weights
    wait_for("actors using weights version >= 1", lambda: all(
        (a.get("last_report") or {}).get("weights_version", -1) >= 1 for a in status()["live_actors"].values()),
        timeout=120)
    # the tiny criterion advances the curriculum and actors are reassigned
    s = wait_for("advance to S2", lambda: (st := status()) and st["stage"] == "S2" and st, timeout=120)
    assert s["advances"] and s["advances"][0]["stage"] == "S2"
    wait_for("actors reassigned to door-corridor", lambda: all(
        (a.get("assignment") or {}).get("world") == "door-corridor" for a in status()["live_actors"].values()),
        timeout=120)
    # the admin call needs its token
    req = urllib.request.Request(cluster.status_url.replace("/status", "/admin/advance"), method="POST", data=b"")
    with pytest.raises(urllib.error.HTTPError) as info:
        urllib.request.urlopen(req, timeout=5)
    assert info.value.code == 401
    # a held-out evaluation of the current step, sent by the evaluator with the admin token, advances
    # a criterion of source: evaluation; a malformed one is refused, one of an older epoch ignored
    def evaluation(body: bytes, token: str = "secret"):
        req = urllib.request.Request(cluster.status_url.replace("/status", "/admin/evaluation"), method="POST",
                                     data=body, headers={"Authorization": f"Bearer {token}"})
        return json.loads(urllib.request.urlopen(req, timeout=5).read())

    for bad, code in ((b'{"epoch": 1}', 400), (b"not json", 400), (b'{"epoch": 1, "success_rate": 2, "episodes": 9}', 400)):
        with pytest.raises(urllib.error.HTTPError) as info:
            evaluation(bad)
        assert info.value.code == code
    with pytest.raises(urllib.error.HTTPError) as info:
        evaluation(b'{"epoch": 1, "success_rate": 1, "episodes": 10}', token="wrong")
    assert info.value.code == 401
    epoch = status()["epoch"]
    assert not evaluation(json.dumps({"epoch": epoch - 1, "success_rate": 1.0, "episodes": 10}).encode())["advanced"]
    assert not evaluation(json.dumps({"epoch": epoch, "success_rate": 0.4, "episodes": 10}).encode())["advanced"]
    reply = evaluation(json.dumps({"epoch": epoch, "success_rate": 0.6, "episodes": 10}).encode())
    assert reply["advanced"] and reply["stage"] == "S3" and status()["stage"] == "S3"
    # 1000 malformed messages on each input key, each from the role allowed to send it (the bus
    # refuses everyone else: tests/test_bus_security.py): counted, nobody dies
    topo = Topology("itest")
    # an actor may put only under its own id (one bus identity per actor): actor-1 sends the garbage
    sessions = {role: cluster.bus_session(role, ident="actor-1") for role in ("actor", "learner", "replay")}
    try:
        publishers = [reliable_publisher(sessions[role], k) for role, k in
                      (("actor", topo.transitions("actor-1")), ("actor", topo.episodes("actor-1")),
                       ("replay", topo.status("replay")), ("learner", topo.weights))]
        for i in range(1000):
            for pub in publishers:
                pub.put(b"\x93garbage" + bytes([i % 256]))
        for i in range(1000):
            for role, key in (("actor", topo.assign), ("learner", topo.sample)):
                for _ in sessions[role].get(key, payload=b"\xc1", timeout=5.0):
                    pass
    finally:
        for session in sessions.values():
            session.close()
    learner_port = cluster.learner_port()
    wait_for("replay rejections counted", lambda: (status()["replay"]["rejected"] or 0) >= 2000, timeout=60)
    wait_for("scheduler rejections counted", lambda: sum(status()["rejected"].values()) >= 3000, timeout=60)
    actor_port = int((cluster.run_dir / "actors" / "actor-0" / "http_port").read_text())
    wait_for("actor weight rejections counted", lambda: metric(
        f"http://127.0.0.1:{actor_port}/metrics", "actor_messages_rejected_total") >= 1000, timeout=60)
    assert cluster.dead() == []
    version = status()["learner"]["version"]
    wait_for("learning goes on", lambda: status()["learner"]["version"] > version, timeout=120)
    # policy artefacts are served with their checksums: v0 at start, then one every 5 s (--export-every-s),
    # so a trained version appears within a few export periods even on a loaded machine
    listing = wait_for("a trained policy version exported", lambda: (
        (got := http_json(f"http://127.0.0.1:{learner_port}/policy/latest"))["version"] >= 1 and got), timeout=60)
    assert listing["version"] >= 1 and "actor.onnx" in listing["files"] and listing["files"]["actor.onnx"]["sha256"]
    # a killed actor leaves /status
    cluster.kill_process("actor-1")
    wait_for("actor-1 gone from /status", lambda: set(status()["live_actors"]) == {"actor-0"}, timeout=30)
    assert cluster.dead() == []


def test_services_carry_on_after_the_router_restarts(tmp_path):
    experiment = resolve_config(overrides=["replay.min_size=200", "replay.samples_per_insert=8", "d4pg.batch_size=128"])
    c = LocalCluster(tmp_path / "run", experiment, actors=1, run="restart", extra={"learner": ["--publish-every", "5"]})
    c.start()
    try:
        before = wait_for("learning under way", lambda: (st := c.status()) and (st["learner"]["version"] or 0) >= 2
                          and st["episodes"] > 0 and st, timeout=300)
        c.kill_process("router")
        c.restart("router")
        wait_for("transitions, episodes and weights flowing again", lambda: (st := c.status())
                 and st["episodes"] > before["episodes"] + 2 and st["learner"]["version"] > before["learner"]["version"] + 2
                 and st["replay"]["size"] > before["replay"]["size"] and len(st["live_actors"]) == 1, timeout=300)
        assert c.dead() == []
    finally:
        c.stop()
