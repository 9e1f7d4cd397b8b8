"""Write docker-stack.yml (for `docker stack deploy`) from docker-compose.yml.

Swarm validates the file against the Compose v3 schema: it needs a `version`, takes
`depends_on` only as a list and ignores `build` and `restart`. Services use DNS round robin and
host-mode ports (see below). Services need no start order:
every curlnav service waits for its router. Run: python scripts/make-stack-file.py
"""

import sys
from pathlib import Path

import yaml

root = Path(__file__).resolve().parent.parent
compose = yaml.safe_load((root / "docker-compose.yml").read_text())
stack = {"version": "3.8", "services": {}, "volumes": compose.get("volumes", {})}
for name, service in compose["services"].items():
    service = dict(service)
    service.pop("build", None)
    service.pop("depends_on", None)
    service.pop("restart", None)
    service.pop("stop_grace_period", None)
    deploy = dict(service.get("deploy", {}))
    deploy.setdefault("restart_policy", {"condition": "on-failure", "max_attempts": 3})
    # DNS round robin, not a virtual IP: services reach each other's containers directly (the
    # VIP's IPVS load balancer is not available on every kernel); published ports bind on the
    # node that runs the task (host mode) for the same reason.
    deploy["endpoint_mode"] = "dnsrr"
    if "ports" in service:
        long_ports = []
        for spec in service["ports"]:
            published, target = spec.rsplit(":", 1)
            long_ports.append({"target": int(target), "published": published, "protocol": "tcp", "mode": "host"})
        service["ports"] = long_ports
    service["deploy"] = deploy
    stack["services"][name] = service
header = ("# Generated from docker-compose.yml by scripts/make-stack-file.py: the same services for\n"
          "# `docker stack deploy -c docker-stack.yml curlnav` (Compose v3 schema, no build or depends_on).\n")
out = root / "docker-stack.yml"
out.write_text(header + yaml.safe_dump(stack, sort_keys=False))
print(f"wrote {out}", file=sys.stderr)
