"""Write docker-stack.yml (for `docker stack deploy`) from docker-compose.yml: the same services over
several Swarm nodes, deployed as `curlnav bench hosts` runs them.

Run: python scripts/make-stack-file.py  (--check: exit 1 if docker-stack.yml is not what it writes).

Placement (what the bench does with network namespaces, `curlnav/bench/hosts.py`):
* `router`: the main node's Zenoh router (the node labelled `curlnav=main`), with the replay,
  learner and scheduler beside it; `router-node`: one router on every other node (`mode: global`),
  joined to the main one over mutual TLS. Both run `curlnav serve router` with the flags of
  `curlnav.bus.mesh.router_flags`, as the bench's routers do: TLS on port 7447 between nodes,
  plain TCP on the node's loopback (127.0.0.1:7448) for its own services.
* Every service uses the node's own network (`host`): each is a client of its node's router at
  127.0.0.1:7448, so actors anywhere reach the run through their local router. The scheduler and
  learner bind their HTTP ports on the main node; the replay's and actors' bind loopback only.
* `actor`: replicas on any node; each takes the bus identity of its task slot (`{{.Task.Slot}}`:
  1..replicas, kept when Swarm replaces a task), `actor-<slot-1>`.

Bus credentials are Docker secrets (swarm has no start order, and a volume lives on one node), each
readable by the image's user only, in /run/secrets. Swarm mounts a service's secrets into every
task of it: each actor task holds every actor identity's password (it authenticates as its own),
and every `router-node` task the one `node` certificate (see docs/guide/bus-security.md).
"""

import argparse
import copy
import re
import sys
from pathlib import Path

import yaml

root = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(root))
from curlnav.bus.mesh import LOCAL_PORT, LOCAL_ROUTER, router_flags  # noqa: E402

IMAGE_UID = "10001"  # the Dockerfile's curlnav user
MAIN = "node.labels.curlnav == main"  # the node of the main router, replay, learner and scheduler
MAIN_ADDRESS = "${CURLNAV_MAIN_ADDRESS:?set CURLNAV_MAIN_ADDRESS to the main node address}"
HOST_NETWORK = "hostnet"
HEADER = """\
# Generated from docker-compose.yml by scripts/make-stack-file.py (do not edit): the run over several
# Swarm nodes, deployed as `curlnav bench hosts` runs it (docs/guide/distributed.md, "Across hosts").
#   1. docker swarm init; join the other nodes; put the image on every node (docker save | docker load);
#      label the main node: docker node update --label-add curlnav=main NODE
#   2. curlnav bus credentials --run compose --out runs/bus --actors {actors} --tls main=MAIN_ADDRESS,node
#   3. CURLNAV_MAIN_ADDRESS=MAIN_ADDRESS docker stack deploy -c docker-stack.yml curlnav  (CURLNAV_BUS=DIR: not runs/bus)
# Routers: `router` on the main node, `router-node` on every other, linked over mutual TLS on port 7447;
# every service is a client of its node's router on 127.0.0.1:7448 (the node's network). Actors: task
# slot s authenticates as actor-<s-1> (at most {actors} replicas: more need more identities and this
# file made again with --max-actors).
"""


def secret(stack: dict, name: str, path: str, target: str) -> dict:
    stack["secrets"][name] = {"file": f"${{CURLNAV_BUS:-./runs/bus}}/{path}"}
    return {"source": name, "target": target, "uid": IMAGE_UID, "mode": 0o400}


def router_secrets(stack: dict, tls_name: str) -> list[dict]:
    """The router's own user, the run's users and access control, the run's CA and its certificate."""
    files = [secret(stack, f"bus-router-{f.replace('.', '-')}", f"router/{f}", f) for f in ("user.json", "users.txt",
                                                                                             "acl.json")]
    files += [secret(stack, f"bus-tls-{f.replace('.', '-')}", f"tls/{f}", f)
              for f in ("ca.pem", f"{tls_name}.pem", f"{tls_name}.key")]
    return files


def http_on(service: dict, target: str, port: str) -> None:
    """Serve HTTP on ``port`` of the node itself (not ``target`` of the container's own network),
    with the healthcheck asking there."""
    command = service["command"]
    command[command.index("--http-port") + 1] = port
    test = service["healthcheck"]["test"]
    test[-1] = test[-1].replace(f"127.0.0.1:{target}/", f"127.0.0.1:{port}/")


def make_stack(compose: dict, max_actors: int) -> dict:
    stack = {"version": "3.8", "services": {},
             "volumes": {k: v for k, v in compose.get("volumes", {}).items() if not k.startswith("bus-")},
             "secrets": {}, "networks": {HOST_NETWORK: {"external": True, "name": "host"}}}
    for name, service in compose["services"].items():
        if name == "credentials":
            continue
        service = copy.deepcopy(service)
        for key in ("build", "depends_on", "restart", "stop_grace_period"):
            service.pop(key, None)
        service["volumes"] = [v for v in service.get("volumes", []) if not v.startswith("bus-")]
        if not service["volumes"]:
            del service["volumes"]
        service["environment"] = {**service["environment"], "CURLNAV_ROUTER": LOCAL_ROUTER,
                                  "CURLNAV_BUS_CREDENTIALS": "/run/secrets"}
        service["networks"] = [HOST_NETWORK]
        deploy = {**service.get("deploy", {}), "restart_policy": {"condition": "on-failure", "max_attempts": 3}}
        service["deploy"] = deploy
        # published ports: the node's own port, bound by the service itself (the node's network)
        for spec in service.pop("ports", []):
            published, target = spec.rsplit(":", 1)
            http_on(service, target, published)
        if name == "router":
            service["command"] = ["router", *router_flags("main")]
            service["healthcheck"]["test"][-1] = (f"import socket; socket.create_connection(('127.0.0.1', {LOCAL_PORT}),"
                                                  f" 2)")
            edge = copy.deepcopy(service)
            service["secrets"] = router_secrets(stack, "main")
            deploy["placement"] = {"constraints": [MAIN]}
            stack["services"]["router"] = service
            edge["command"] = ["router", *router_flags("node", MAIN_ADDRESS)]
            edge["secrets"] = router_secrets(stack, "node")
            edge["deploy"] = {**edge["deploy"], "mode": "global",
                              "placement": {"constraints": [MAIN.replace("==", "!=")]}}
            stack["services"]["router-node"] = edge
            continue
        if name == "actor":
            # several actors on one node: any free port, read back from the actor's own folder
            service["command"][service["command"].index("--http-port") + 1] = "0"
            service["healthcheck"]["test"][-1] = (
                "import glob, urllib.request; port = open(glob.glob('/data/actors/*/http_port')[0]).read().strip(); "
                "urllib.request.urlopen(f'http://127.0.0.1:{port}/metrics', timeout=3)")
            service["environment"].update({"CURLNAV_ACTOR_SLOT": "{{.Task.Slot}}", "CURLNAV_HTTP_HOST": "127.0.0.1"})
            service["secrets"] = [secret(stack, f"bus-actor-{n}-user-json", f"actor-{n}/user.json",
                                         f"actor-{n}/user.json") for n in range(max_actors)]
        else:
            service["secrets"] = [secret(stack, f"bus-{name}-user-json", f"{name}/user.json", "user.json")]
            deploy["placement"] = {"constraints": [MAIN]}
            if name == "replay":
                service["environment"]["CURLNAV_HTTP_HOST"] = "127.0.0.1"  # asked by its healthcheck only
        stack["services"][name] = service
    return stack


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if docker-stack.yml differs from what would be written")
    ap.add_argument("--max-actors", type=int, default=None,
                    help="actor identities the stack mounts (default: the compose file's CURLNAV_MAX_ACTORS default)")
    args = ap.parse_args()
    compose = yaml.safe_load((root / "docker-compose.yml").read_text())
    default = compose["services"]["credentials"]["environment"]["CURLNAV_MAX_ACTORS"]
    max_actors = args.max_actors or int(re.fullmatch(r"\$\{CURLNAV_MAX_ACTORS:-(\d+)\}", default).group(1))
    text = HEADER.format(actors=max_actors) + yaml.safe_dump(make_stack(compose, max_actors), sort_keys=False)
    out = root / "docker-stack.yml"
    if args.check:
        if out.read_text() != text:
            print(f"{out} is not what scripts/make-stack-file.py writes: run it again", file=sys.stderr)
            return 1
        return 0
    out.write_text(text)
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
