"""The routers of a run over several hosts: one per host, linked over mutual TLS.

One function says how each host's router runs (``router_flags``), and both ``curlnav bench
hosts`` (hosts as network namespaces) and the Swarm stack file (``scripts/make-stack-file.py``:
``docker-stack.yml``) take their router command lines from it, so the deployment the docs describe
is the one the bench runs (``tests/test_deploy_stack_file.py`` checks both).

* Every router listens on ``tls/0.0.0.0:MESH_PORT`` for the other hosts' routers (mutual TLS with
  the run's CA, its certificate ``--tls NAME`` from ``curlnav bus credentials --tls NAME=ADDRESS``)
  and on ``LOCAL_ROUTER`` (plain TCP on the host's loopback, never reachable from another host) for
  the services of its own host, which are its clients (``CURLNAV_ROUTER``).
* The main host's router (the replay, learner and scheduler run there) connects to nobody; every
  other host's router connects to it, ``tls/<main address>:MESH_PORT``. Zenoh routes between them.
"""

from __future__ import annotations

MESH_PORT = 7447  # routers of other hosts, mutual TLS
LOCAL_PORT = 7448  # the host's own services, plain TCP on loopback
LOCAL_ROUTER = f"tcp/127.0.0.1:{LOCAL_PORT}"  # every service's router endpoint (CURLNAV_ROUTER)


def router_flags(name: str, main_address: str | None = None) -> list[str]:
    """``curlnav serve router`` flags of router ``name`` (its TLS certificate): the main host's
    (``main_address`` None) or another host's, which joins the main router at ``main_address``."""
    flags = ["--tls", name, "--listen", f"tls/0.0.0.0:{MESH_PORT},{LOCAL_ROUTER}"]
    if main_address is not None:
        flags += ["--connect", f"tls/{main_address}:{MESH_PORT}"]
    return flags
