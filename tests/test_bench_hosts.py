"""Across hosts (issue 30): hosts as network namespaces, a Zenoh router in each, the routers
linked by mutual TLS with the run's CA. A partition of an actor host loses nothing and its actors
come back; a router with plain TCP or another CA's certificate is never linked. Needs root and
``ip netns`` (skipped otherwise, with the reason). Every namespace, link and process is removed."""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap

import pytest
from conftest import stop_all

from curlnav.bench.netns import Hosts, unavailable
from curlnav.bus.mesh import LOCAL_ROUTER, MESH_PORT, router_flags
from curlnav.bus.security import make_credentials, make_tls

WHY = unavailable()
pytestmark = [pytest.mark.skipif(WHY is not None, reason=f"no network namespaces here: {WHY}"), pytest.mark.slow, pytest.mark.net]


def test_a_partition_loses_nothing_the_actors_come_back_and_training_goes_on(tmp_path):
    """A cut longer than Zenoh's 10 s link lease: the routers drop the cut-off host's session (its
    actor leaves /status), and after the heal they open a clean one (it comes back and resends).
    Before the routers bounded unacknowledged data on their links (``LinkAckTimeout``), host 0's
    router kept a stale session whose TLS close hung on the dead peer, and the actor did not come
    back within the heal phase."""
    from curlnav.bench.hosts import run_hosts_bench
    from curlnav.config import resolve_config

    fast = resolve_config(overrides=["replay.min_size=100", "exploration.warmup_steps=100", "d4pg.batch_size=32"])
    result = run_hosts_bench(hosts=3, actors_per_host=1, partition_s=16, around_s=8, run_dir=str(tmp_path / "run"),
                             experiment=fast, startup_s=120)
    cut, heal = result["phases"][1], result["phases"][2]
    assert cut["live_end"] == {1: 0, 2: 1}, "the cut-off actor's token did not go within the partition"
    assert heal["live_end"] == {1: 1, 2: 1}, "the actors are not back in /status"
    assert result["lost"] == 0 and result["generated"] > 0, result["summary"]
    assert result["after_heal"] > 0 and result["v1"] > result["v0"], result["summary"]  # training went on
    assert all(f["unacknowledged_batches"] == 0 for f in result["finals"]) and len(result["finals"]) == 2


LISTENER = textwrap.dedent('''
    import os, sys, time
    from curlnav.bus.security import load_user
    from curlnav.bus.transport import open_session
    role, bus, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
    s = open_session("tcp/127.0.0.1:7448", 20, user=load_user(bus, role, "mesh", "actor-0" if role == "actor" else None))
    got = []
    if role == "actor":
        s.declare_subscriber("curlnav/mesh/weights", lambda x: got.append(1))
    end = time.time() + seconds
    while time.time() < end:
        if role == "learner":
            s.put("curlnav/mesh/weights", b"w")
        time.sleep(0.2)
    print("received", len(got), flush=True)
    os._exit(0)  # a zenoh session may hang at interpreter exit
''')


def test_a_plain_tcp_or_wrong_ca_router_cannot_join_the_mesh(tmp_path):
    bus, evil = tmp_path / "bus", tmp_path / "evil"
    with Hosts(4, tag=f"t{tmp_path.name[-3:]}") as net:
        make_credentials(bus, "mesh", actors=1, tls_hosts={f"h{i}": net.address(i) for i in range(4)})
        shutil.copytree(bus, evil)  # the intruder knows every password ...
        shutil.rmtree(evil / "tls")
        make_tls(evil / "tls", {"h2": net.address(2)})  # ... but its certificate is from another CA
        script = tmp_path / "listen.py"
        script.write_text(LISTENER)
        procs = []

        def start(i: int, *args: str, out=None) -> subprocess.Popen:
            procs.append(subprocess.Popen([*net.exec(i), sys.executable, *args], stdout=out or subprocess.DEVNULL,
                                          stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True))
            return procs[-1]

        def router(i: int, credentials, *args: str) -> None:
            start(i, "-m", "curlnav.cli", "serve", "router", "--run", "mesh", "--bus-credentials", str(credentials),
                  *args)

        try:
            a0 = net.address(0)
            # the routers of the bench and the stack file (router_flags), and one that links plain TCP
            router(0, bus, *router_flags("h0"))
            router(1, bus, *router_flags("h1", a0))
            router(2, evil, *router_flags("h2", a0))
            router(3, bus, "--listen", LOCAL_ROUTER, "--connect", f"tcp/{a0}:{MESH_PORT}")  # plain TCP
            listeners = {i: start(i, str(script), "actor", str(bus), "25", out=subprocess.PIPE) for i in (1, 2, 3)}
            start(0, str(script), "learner", str(bus), "25")
            received = {}
            for i, proc in listeners.items():
                out, _ = proc.communicate(timeout=80)
                received[i] = int(out.strip().rsplit(" ", 1)[-1]) if "received" in out else None
            assert received[1] and received[1] > 0, f"the control: the TLS router with the run's CA relays ({out})"
            assert received[2] == 0, "a router with another CA's certificate was linked"
            assert received[3] == 0, "a plain-TCP router was linked"
        finally:
            stop_all(procs)
