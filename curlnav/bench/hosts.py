"""``curlnav bench hosts``: a run over several hosts that survives a partition.

Hosts are Linux network namespaces on one bridge (``curlnav.bench.netns``, root). Each runs its own
Zenoh router; the actor hosts' routers connect to host 0's over **mutual TLS** with the run's CA
and one certificate per router, made by ``curlnav bus credentials --tls`` (``make_credentials``).
Every service is a client of its own host's router (plain TCP on the host's loopback); host 0
runs the replay, learner and scheduler, the others the actors, each with its own bus identity.
Each host is given only its own credentials (``h<i>/bus``, ``host_credentials``): its router's
dictionary, access control, the CA's certificate and its own certificate and key (``router/``); its
services' own folders (an actor: its ``user.json`` alone). The CA's key and the other routers' keys stay
in the folder where the launcher (the main host) minted them.
The routers run with ``curlnav.bus.mesh.router_flags``, as the Swarm stack file's do.

Phases: train, cut one actor host off (its link down) for the partition, heal it, train on; then
the actors stop, send what they still hold and wait for its acknowledgement (the final flush),
and the replay's count is read. Per phase: actors live per host, transitions accepted per second,
weights version and policy lag. The last line::

    hosts H, actors A, partition S s: generated G, accepted N, accepted after heal X, dropped by the replay R,
    lost L, duplicates D, learner v V0 -> V1

G: transitions the actors put into batches; N: transitions the replay accepted (in its log); X: of
those, accepted after the heal; R: accepted transitions the replay could not store; L = G - N + R;
D: batches the replay dropped as already accepted (resends whose acknowledgement had not arrived);
V0 -> V1: the learner's version when the partition began and at the end.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
import urllib.request
from pathlib import Path

from curlnav.bench.faults import poll
from curlnav.bench.netns import Hosts
from curlnav.bus.mesh import LOCAL_ROUTER, router_flags
from curlnav.run.launch import LocalCluster, http_json_or_none

SCHEDULER_PORT, LEARNER_PORT = 8080, 8081  # on host 0's address (each host has its own ports)
HELP = ("a run over network namespaces (a router per host, TLS between them): cut an actor host off, heal, train on; "
        "what was lost (root)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--hosts", type=int, default=3, help="namespaces: host 0 runs replay, learner and scheduler")
    p.add_argument("--actors-per-host", type=int, default=2, help="actors on each of hosts 1..H-1")
    p.add_argument("--partition-s", type=float, default=20.0, help="seconds host 1 stays cut off (its link down)")
    p.add_argument("--minutes", type=float, default=None, help="the whole run (default: 30 s before and after)")
    p.add_argument("--netem", default="", help="latency and loss on the actor hosts' links, as tc netem takes "
                                               "them (e.g. 'delay 20ms loss 1%%'), where the kernel has netem")
    p.add_argument("--run-dir", default="runs/bench-hosts")


def main(args: argparse.Namespace) -> int:
    from curlnav.bench.netns import unavailable

    why = unavailable()
    if why:
        raise SystemExit(f"curlnav: error: bench hosts needs network namespaces: {why}")
    result = run_hosts_bench(hosts=args.hosts, actors_per_host=args.actors_per_host, partition_s=args.partition_s,
                             minutes=args.minutes, run_dir=args.run_dir, netem=args.netem)
    return 0 if result["lost"] == 0 else 1


class HostsCluster(LocalCluster):
    """A run over the namespaces of ``net``: a router per host, the services on host 0, actors
    (``actors_per_host``) on every other host."""

    def __init__(self, run_dir: str | Path, net: Hosts, experiment=None, actors_per_host: int = 2,
                 run: str = "hosts", extra: dict[str, list[str]] | None = None) -> None:
        from curlnav.bus.security import make_credentials

        super().__init__(run_dir, experiment, actors=(net.count - 1) * actors_per_host, run=run,
                         extra=extra, scheduler_port=SCHEDULER_PORT, learner_port=LEARNER_PORT)
        self.net, self.actors_per_host = net, actors_per_host
        make_credentials(self.bus_dir, run, actors=self.actors,
                         tls_hosts={self.host_name(i): net.address(i) for i in range(net.count)})
        self.router = LOCAL_ROUTER

    @staticmethod
    def host_name(i: int) -> str:
        return f"h{i}"

    def host_of(self, actor: str) -> int:
        """The host of actor ``actor-<n>``."""
        return 1 + int(actor.rsplit("-", 1)[1]) // self.actors_per_host

    def host_credentials(self, i: int) -> Path:
        """Host ``i``'s own credentials, ``h<i>/bus``: its router's (with its TLS pair), and the
        replay's, learner's and scheduler's (host 0) or its actors' (the others)."""
        from curlnav.bus.security import host_credentials

        users = ["router", *(("replay", "learner", "scheduler") if i == 0 else
                             (f"actor-{n}" for n in range(self.actors) if self.host_of(f"actor-{n}") == i))]
        return host_credentials(self.bus_dir, self.run_dir / self.host_name(i) / "bus", users,
                                router=self.host_name(i))

    def host_command(self, i: int, role: str, *more: str, identity: str = "") -> list[str]:
        """``curlnav serve role`` on host ``i``, given only ``identity``'s credentials (default: the
        role's; the router's holds its TLS pair too)."""
        credentials = self.run_dir / self.host_name(i) / "bus" / (identity or role)
        return [*self.net.exec(i), sys.executable, "-m", "curlnav.cli", "serve", role, "--run", self.run,
                "--router", self.router, "--data-dir", str(self.run_dir / self.host_name(i)),
                "--http-host", self.net.address(i), "--config", str(self.config_path),
                "--bus-credentials", str(credentials), *self.extra.get(role, []), *more]

    def router_command(self, i: int, tls_name: str | None = None) -> list[str]:
        """Host ``i``'s router (``router_flags``): TLS to the other hosts (as ``tls_name``), TCP on its
        loopback; host 0's is the main one, the others join it."""
        main = None if i == 0 else self.net.address(0)
        return self.host_command(i, "router", *router_flags(tls_name or self.host_name(i), main))

    def start(self) -> None:
        for i in range(self.net.count):
            self.host_credentials(i)
        for i in range(self.net.count):
            self.spawn(f"router-{self.host_name(i)}", self.router_command(i))
        self.spawn("replay", self.host_command(0, "replay"))
        self.spawn("learner", self.host_command(0, "learner", "--threads", "1", "--http-port", str(LEARNER_PORT)))
        self.spawn("scheduler", self.host_command(0, "scheduler", "--http-port", str(SCHEDULER_PORT)))
        for n in range(self.actors):
            self.start_actor(n)

    def start_actor(self, n: int):
        return self.spawn(f"actor-{n}", self.host_command(self.host_of(f"actor-{n}"), "actor", "--actor-id",
                                                          f"actor-{n}", "--actor-index", str(n),
                                                          "--actor-count", str(self.actors), identity=f"actor-{n}"))

    @property
    def status_url(self) -> str:
        return f"http://{self.net.address(0)}:{SCHEDULER_PORT}/status"

    @property
    def learner_url(self) -> str:
        return f"http://{self.net.address(0)}:{LEARNER_PORT}"

    def replay_url(self) -> str | None:
        try:
            port = int((self.run_dir / "h0" / "replay" / "http_port").read_text())
        except (OSError, ValueError):
            return None
        return f"http://{self.net.address(0)}:{port}"

    def replay_counts(self) -> dict | None:
        """The replay's own figures: accepted transitions and refused batches by reason."""
        url = self.replay_url()
        health = url and http_json_or_none(f"{url}/healthz")
        if not health:
            return None
        rejected: dict[str, float] = {}
        try:
            with urllib.request.urlopen(f"{url}/metrics", timeout=3) as response:
                for line in response.read().decode().splitlines():
                    if line.startswith("replay_messages_rejected_total{"):
                        reason = line.split('reason="', 1)[1].split('"', 1)[0]
                        rejected[reason] = float(line.rsplit(" ", 1)[1])
        except (OSError, ValueError, IndexError):
            pass
        return {"accepted": int(health.get("accepted") or 0), "dropped": int(health.get("dropped") or 0),
                "rejected": rejected}

    def live_per_host(self, status: dict | None) -> dict[int, int]:
        live = list((status or {}).get("live_actors") or {})
        return {i: sum(1 for a in live if a.startswith("actor-") and self.host_of(a) == i)
                for i in range(1, self.net.count)}

    def finals(self) -> list[dict]:
        out = []
        for path in sorted(self.run_dir.glob("h*/actors/*/actor-final.json")):
            try:
                out.append(json.loads(path.read_text()))
            except (OSError, ValueError):
                pass
        return out


def bench_experiment():
    """A small, fast config: the bench measures the transport, not learning."""
    from curlnav.config import resolve_config

    return resolve_config(overrides=["replay.min_size=300", "exploration.warmup_steps=300"])


class Phases:
    """Per-phase figures, from the scheduler's status and the replay's counts."""

    def __init__(self, cluster: HostsCluster) -> None:
        self.cluster = cluster
        self.rows: list[dict] = []

    def snapshot(self) -> dict:
        status = self.cluster.status() or {}
        counts = self.cluster.replay_counts() or {}
        return {"t": time.monotonic(), "status": status, "accepted": counts.get("accepted"),
                "version": (status.get("learner") or {}).get("version")}

    def run(self, name: str, seconds: float, every: float = 5.0) -> dict:
        """Wait ``seconds`` (sampling the live actors every ``every`` s), then one line of figures."""
        first = self.snapshot()
        live_min: dict[int, int] = {}
        live_last: dict[int, int] = {}
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            time.sleep(min(every, max(0.0, deadline - time.monotonic())))
            live_last = self.cluster.live_per_host(self.cluster.status())
            live_min = {i: min(n, live_min.get(i, n)) for i, n in live_last.items()}
        last = self.snapshot()
        span = max(last["t"] - first["t"], 1e-6)
        accepted = None if first["accepted"] is None or last["accepted"] is None else last["accepted"] - first["accepted"]
        row = {"phase": name, "seconds": span, "live_min": live_min, "live_end": live_last,
               "transitions_per_s": None if accepted is None else accepted / span, "accepted": last["accepted"],
               "version": last["version"], "policy_lag": last["status"].get("policy_lag")}
        self.rows.append(row)
        hosts = ", ".join(f"h{i} {live_min.get(i, 0)}-{live_last.get(i, 0)}" for i in sorted(live_last))
        rate = "-" if row["transitions_per_s"] is None else f"{row['transitions_per_s']:.1f}"
        lag = "-" if row["policy_lag"] is None else f"{row['policy_lag']:.1f}"
        print(f"phase {name:<9} {span:5.1f} s: actors live per host (min-end) {hosts}; transitions/s {rate}; "
              f"weights v{row['version']}; policy lag {lag}", flush=True)
        return row


def run_hosts_bench(hosts: int = 3, actors_per_host: int = 2, partition_s: float = 20.0,
                    minutes: float | None = None, run_dir: str = "runs/bench-hosts", cut: int = 1,
                    netem: str = "", startup_s: float = 300.0, experiment=None, around_s: float | None = None) -> dict:
    """Start the run over ``hosts`` namespaces, train, cut host ``cut`` off for ``partition_s``,
    heal, train on (``minutes`` in all, else 30 s before and after), flush; print the phases and
    the summary line and return the figures (``summary``: the line)."""
    if hosts < 2:
        raise ValueError("--hosts: at least 2 (host 0 runs the services, the others actors)")
    if not 1 <= cut < hosts:
        raise ValueError(f"the host to cut off is one of the actor hosts 1..{hosts - 1}")
    around = around_s or (30.0 if minutes is None else max(10.0, (minutes * 60 - partition_s) / 2))
    shutil.rmtree(run_dir, ignore_errors=True)
    net = Hosts(hosts).setup()
    cluster = None
    try:
        for i in range(1, hosts):
            if netem:
                why = net.netem(i, netem)
                print(f"netem {netem!r} on h{i}: " + ("on" if why is None else f"not available ({why})"), flush=True)
        cluster = HostsCluster(Path(run_dir), net, experiment or bench_experiment(), actors_per_host,
                               extra={"learner": ["--publish-every", "20"]})
        print(f"{hosts} hosts (namespaces {net.ns(0)}..{net.ns(hosts - 1)}, {net.subnet}.0/24), routers linked by "
              f"mutual TLS, {cluster.actors} actors on h1..h{hosts - 1}; starting...", flush=True)
        cluster.start()
        started = time.monotonic()
        ready = poll(lambda: (s := cluster.status()) and (s.get("learner") or {}).get("version")
                     and sum(cluster.live_per_host(s).values()) == cluster.actors
                     and ((cluster.replay_counts() or {}).get("accepted") or 0) > 0 and s, startup_s, every=1.0)
        if not ready:
            dead = cluster.dead()
            raise RuntimeError(f"the run did not start within {startup_s:.0f} s (exited: {dead or 'none'}); "
                               f"logs in {run_dir}/logs")
        print(f"training after {time.monotonic() - started:.0f} s", flush=True)
        phases = Phases(cluster)
        phases.run("train", around)
        net.cut(cut)
        v0 = phases.rows[-1]["version"]
        phases.run("partition", partition_s)
        net.heal(cut)
        healed = phases.snapshot()
        phases.run("heal", around)
        # the final flush: actors stop, send what they hold, wait for its acknowledgement
        cluster._stop_all([n for n in list(cluster.processes) if n.startswith("actor-")], timeout=60)
        time.sleep(2.0)
        counts = poll(cluster.replay_counts, 10.0) or {}
        status = cluster.status() or {}
        finals = cluster.finals()
        generated = sum(int(f.get("generated") or 0) for f in finals)
        accepted = int(counts.get("accepted") or 0)
        after_heal = accepted - int(healed["accepted"] or 0)
        duplicates = int(counts.get("rejected", {}).get("duplicate", 0))
        dropped = int(counts.get("dropped") or 0)  # accepted, but not stored by the replay: lost too
        lost = generated - accepted + dropped
        v1 = (status.get("learner") or {}).get("version")
        summary = (f"hosts {hosts}, actors {cluster.actors}, partition {partition_s:g} s: generated {generated}, "
                   f"accepted {accepted}, accepted after heal {after_heal}, dropped by the replay {dropped}, lost {lost}, "
                   f"duplicates {duplicates}, learner v {v0} -> {v1}")
        unacked = sum(int(f.get("unacknowledged_batches") or 0) for f in finals)
        print(f"final flush: {len(finals)}/{cluster.actors} actors reported, {unacked} batches unacknowledged at "
              f"exit, refused by the replay {counts.get('rejected', {})}", flush=True)
        print(summary, flush=True)
        return {"phases": phases.rows, "generated": generated, "accepted": accepted, "after_heal": after_heal,
                "lost": lost, "dropped": dropped, "duplicates": duplicates, "v0": v0, "v1": v1, "finals": finals,
                "summary": summary, "rejected": counts.get("rejected", {})}
    finally:
        if cluster is not None:
            cluster.stop()
        net.teardown()
