"""Fault injection on a running ``docker compose`` training (the Docker Python SDK): SIGKILL the
replay, learner and scheduler containers in turn, start each again, and print what was lost
(``curlnav.bench.faults.measure_kill``, through the scheduler's published /status).

    python scripts/compose_faults.py --project curlnavsmoke --status http://127.0.0.1:18080/status

Exit code 1 if anything accepted was lost, a version went back, or a service did not come back.
"""

from __future__ import annotations

import argparse
import sys
import time

import docker
from curlnav.bench.faults import FaultTarget, measure_kill, print_rows


def container_of(client, project: str, service: str):
    found = client.containers.list(filters={"label": [f"com.docker.compose.project={project}",
                                                      f"com.docker.compose.service={service}"]})
    if not found:
        raise SystemExit(f"no running container of service {service!r} in compose project {project!r}")
    return found[0]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--project", required=True, help="compose project name")
    p.add_argument("--status", required=True, help="the scheduler's /status URL")
    p.add_argument("--pause-s", type=float, default=10.0, help="s of training between kills")
    args = p.parse_args()
    client = docker.from_env()
    rows = []
    for name in ("replay", "learner", "scheduler"):
        container = container_of(client, args.project, name)
        target = FaultTarget(name, kill=lambda c=container: c.kill(signal="SIGKILL"),
                             start=lambda c=container: c.start())
        rows.append(measure_kill(target, args.status))
        print_rows(rows[-1:])
        time.sleep(args.pause_s)
    ok = all(r.get("lost", 0) == 0 and r.get("forward", True) and r.get("back_s") is not None for r in rows)
    print("fault injection: " + ("nothing lost, every service back" if ok else "FAILED (see above)"), flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
