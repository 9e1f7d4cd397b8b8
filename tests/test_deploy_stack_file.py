"""The multi-host deployment the docs describe is the one the hosts bench runs (issue 30).

``docker-stack.yml`` is generated (``scripts/make-stack-file.py``) and must be what the script
writes; its routers run with the flags of ``curlnav.bus.mesh.router_flags``, as
``curlnav bench hosts``' routers do (a router per node, the others joined to the main one over
mutual TLS, every service a client of its node's router on loopback); the credentials its header
tells users to make hold every secret it mounts; Docker reads it (``docker stack config``, where
the client is installed). The bench itself runs in ``tests/test_bench_hosts.py``; a real single-node
swarm deploy in ``scripts/compose-smoke.sh``."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import Namespaces

from curlnav.bench.hosts import HostsCluster
from curlnav.bus.identity import actor_identities
from curlnav.bus.mesh import LOCAL_ROUTER, router_flags

ROOT = Path(__file__).resolve().parent.parent
STACK = ROOT / "docker-stack.yml"
MAIN_ADDRESS = "${CURLNAV_MAIN_ADDRESS:?set CURLNAV_MAIN_ADDRESS to the main node address}"
MAIN, OTHERS = "node.labels.curlnav == main", "node.labels.curlnav != main"


def stack() -> dict:
    return yaml.safe_load(STACK.read_text())


@pytest.mark.slow
def test_the_stack_file_is_what_the_script_writes():
    result = subprocess.run([sys.executable, "scripts/make-stack-file.py", "--check"], cwd=ROOT, capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 0, result.stderr


def bench_commands(tmp_path) -> dict[str, list[str]]:
    """What ``curlnav bench hosts`` starts on 3 hosts (1 actor per actor host), by service name."""
    cluster = HostsCluster(tmp_path / "run", Namespaces(), actors_per_host=1)
    started = {}
    cluster.spawn = lambda name, cmd: started.setdefault(name, cmd)
    cluster.start()
    return {name: cmd[cmd.index("serve") + 1:] for name, cmd in started.items()}


def flag(command: list[str], name: str) -> str:
    return command[command.index(name) + 1]


def test_the_stack_routers_run_as_the_hosts_bench_runs_them(tmp_path):
    services = stack()["services"]
    assert services["router"]["command"] == ["router", *router_flags("main")]
    assert services["router-node"]["command"] == ["router", *router_flags("node", MAIN_ADDRESS)]
    bench = bench_commands(tmp_path)
    assert sorted(bench) == ["actor-0", "actor-1", "learner", "replay", "router-h0", "router-h1", "router-h2",
                             "scheduler"]
    # the bench's routers: host 0's the main one, the others joined to it, with the same flags
    assert bench["router-h0"][-len(router_flags("h0")):] == router_flags("h0")
    assert bench["router-h2"][-len(router_flags("h2", "10.9.0.1")):] == router_flags("h2", "10.9.0.1")
    assert router_flags("h2", "10.9.0.1") == ["--tls", "h2", "--listen", "tls/0.0.0.0:7447,tcp/127.0.0.1:7448",
                                              "--connect", "tls/10.9.0.1:7447"]
    # every service a client of its own host's router: in the bench and in the stack
    assert {name: flag(cmd, "--router") for name, cmd in bench.items() if not name.startswith("router")} == \
        {name: LOCAL_ROUTER for name in bench if not name.startswith("router")}
    assert {name: s["environment"]["CURLNAV_ROUTER"] for name, s in services.items()} == \
        {name: LOCAL_ROUTER for name in services}


def test_the_stack_places_a_router_on_every_node_and_the_services_on_the_main_one():
    services = stack()["services"]
    assert set(services) == {"router", "router-node", "replay", "learner", "scheduler", "actor"}
    for name in ("router", "replay", "learner", "scheduler"):
        assert services[name]["deploy"]["placement"]["constraints"] == [MAIN], name
    assert services["router-node"]["deploy"]["mode"] == "global"
    assert services["router-node"]["deploy"]["placement"]["constraints"] == [OTHERS]
    assert "placement" not in services["actor"]["deploy"]  # actors on any node, beside its router
    assert all(s["networks"] == ["hostnet"] for s in services.values())  # the node's own loopback
    assert stack()["networks"]["hostnet"] == {"external": True, "name": "host"}
    assert "ports" not in str(services)  # nothing published through Swarm's mesh: services bind the node's ports


def test_each_actor_task_authenticates_as_the_identity_of_its_slot():
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    default = compose["services"]["credentials"]["environment"]["CURLNAV_MAX_ACTORS"]
    max_actors = int(re.fullmatch(r"\$\{CURLNAV_MAX_ACTORS:-(\d+)\}", default).group(1))
    actor = stack()["services"]["actor"]
    assert actor["environment"]["CURLNAV_ACTOR_SLOT"] == "{{.Task.Slot}}"
    assert actor["environment"]["CURLNAV_BUS_CREDENTIALS"] == "/run/secrets"
    assert [s["target"] for s in actor["secrets"]] == [f"actor-{n}/user.json" for n in range(max_actors)]
    assert all(s["uid"] == "10001" and s["mode"] == 0o400 for s in actor["secrets"])


@pytest.mark.slow
def test_the_credentials_the_header_asks_for_hold_every_secret_the_stack_mounts(tmp_path):
    text = STACK.read_text()
    line = next(line for line in text.splitlines() if "curlnav bus credentials" in line)
    args = shlex.split(line.split("2. ", 1)[1].replace("MAIN_ADDRESS", "10.9.0.1"))
    assert args[:3] == ["curlnav", "bus", "credentials"]
    out = tmp_path / "bus"
    args = [str(out) if a == "runs/bus" else a for a in args[3:]]
    result = subprocess.run([sys.executable, "-m", "curlnav.cli", "bus", "credentials", *args], capture_output=True,
                            text=True, timeout=120, env={**os.environ, "CURLNAV_MAX_ACTORS": "1"})
    assert result.returncode == 0, result.stderr
    files = [s["file"].replace("${CURLNAV_BUS:-./runs/bus}", str(out)) for s in stack()["secrets"].values()]
    assert [f for f in files if not Path(f).is_file()] == []
    assert len(actor_identities(out)) == len(stack()["services"]["actor"]["secrets"])
    acl = (out / "router" / "acl.json").read_text()
    assert '"router-main"' in acl and '"router-node"' in acl  # both certificates may link


@pytest.mark.slow
@pytest.mark.docker
@pytest.mark.skipif(shutil.which("docker") is None, reason="no docker client")
def test_docker_reads_the_stack_file():
    env = {**os.environ, "CURLNAV_MAIN_ADDRESS": "10.9.0.1"}
    result = subprocess.run(["docker", "stack", "config", "-c", "docker-stack.yml"], cwd=ROOT, capture_output=True,
                            text=True, timeout=60, env=env)
    if "unknown command" in result.stderr or "is not a docker command" in result.stderr:
        pytest.skip("this docker client has no `stack config`")
    assert result.returncode == 0, result.stderr
    assert "tls/10.9.0.1:7447" in result.stdout
    unset = subprocess.run(["docker", "stack", "config", "-c", "docker-stack.yml"], cwd=ROOT, capture_output=True,
                           text=True, timeout=60, env={k: v for k, v in env.items() if k != "CURLNAV_MAIN_ADDRESS"})
    assert unset.returncode != 0 and "CURLNAV_MAIN_ADDRESS" in unset.stderr
