"""Write docker-stack.yml (for `docker stack deploy`) from docker-compose.yml.

Swarm validates the file against the Compose v3 schema: it needs a `version`, takes
`depends_on` only as a list and ignores `build` and `restart`. Services use DNS round robin and
host-mode ports (see below). Services need no start order:
every curlnav service waits for its router. Run: python scripts/make-stack-file.py

Bus credentials: Docker secrets instead of compose's one-shot `credentials` service and its
volumes (swarm has no start order, and a volume lives on one node). Each service gets only its
own role's files, readable by the image's user only, in /run/secrets. Make them first, on the
node that deploys: `curlnav bus credentials --run compose --out runs/bus --shared-actor` (CURLNAV_BUS: another
folder; the same --run as CURLNAV_RUN).
"""

import sys
from pathlib import Path

import yaml

root = Path(__file__).resolve().parent.parent
compose = yaml.safe_load((root / "docker-compose.yml").read_text())
BUS_FILES = {"router": ("user.json", "users.txt", "acl.json")}  # other roles: user.json
IMAGE_UID = "10001"  # the Dockerfile's curlnav user
stack = {"version": "3.8", "services": {},
         "volumes": {k: v for k, v in compose.get("volumes", {}).items() if not k.startswith("bus-")}, "secrets": {}}
for name, service in compose["services"].items():
    if name == "credentials":
        continue
    service = dict(service)
    bus = [v for v in service.get("volumes", []) if v.startswith("bus-")]
    if bus:
        role = bus[0].split(":")[0].removeprefix("bus-")
        service["volumes"] = [v for v in service["volumes"] if v not in bus]
        if not service["volumes"]:
            del service["volumes"]
        service["environment"] = {**service["environment"], "CURLNAV_BUS_CREDENTIALS": "/run/secrets"}
        service["secrets"] = []
        for file in BUS_FILES.get(role, ("user.json",)):
            secret = f"bus-{role}-{file.replace('.', '-')}"
            stack["secrets"][secret] = {"file": f"${{CURLNAV_BUS:-./runs/bus}}/{role}/{file}"}
            service["secrets"].append({"source": secret, "target": file, "uid": IMAGE_UID, "mode": 0o400})
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
          "# `docker stack deploy -c docker-stack.yml curlnav` (Compose v3 schema, no build or depends_on).\n"
          "# Bus credentials are Docker secrets: first `curlnav bus credentials --run compose --out runs/bus --shared-actor`\n"
          "# (CURLNAV_BUS: another folder).\n")
out = root / "docker-stack.yml"
out.write_text(header + yaml.safe_dump(stack, sort_keys=False))
print(f"wrote {out}", file=sys.stderr)
