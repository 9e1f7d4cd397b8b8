"""Run the services: one role per process (``curlnav serve ROLE``, the container entry point), or
all of them as local processes (``curlnav train``, the embedded default)."""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

ROLES = ("router", "replay", "learner", "scheduler", "actor")


def env_default(name: str, default):
    """Deployment settings from ``CURLNAV_<NAME>`` environment variables (containers) or a default."""
    value = os.environ.get(f"CURLNAV_{name.upper()}")
    if value is None:
        return default
    return type(default)(value) if default is not None and not isinstance(default, bool) else value


def add_serve_arguments(p) -> None:
    """``curlnav serve ROLE``: deployment options, plus the experiment config (``--preset``,
    ``--config``, ``--set``, ``--world``, ``--curriculum``), which every service of a run must share."""
    from .experiment_cli import add_config_arguments

    p.add_argument("role", choices=ROLES)
    p.add_argument("--run", default=env_default("run", "default"), help="run name: the Zenoh key prefix")
    p.add_argument("--router", default=env_default("router", "tcp/127.0.0.1:7447"), help="Zenoh router endpoint")
    p.add_argument("--listen", default=env_default("listen", "tcp/0.0.0.0:7447"), help="router: listen endpoint")
    p.add_argument("--connect", default=env_default("connect", ""),
                   help="router: other routers to join, comma-separated endpoints (multi-host)")
    p.add_argument("--data-dir", default=env_default("data_dir", "runs/service"), help="state folder (per role below it)")
    p.add_argument("--http-port", type=int, default=env_default("http_port", 0))
    p.add_argument("--admin-token", default=env_default("admin_token", ""), help="scheduler: admin bearer token")
    p.add_argument("--actor-id", default=env_default("actor_id", ""), help="actor: id (default host-pid)")
    p.add_argument("--actor-index", type=int, default=env_default("actor_index", -1),
                   help="actor: rung of the sigma ladder and seed offset (default: from the actor id)")
    p.add_argument("--actor-count", type=int, default=env_default("actor_count", 1),
                   help="actor: actors in the run (each takes this share of the warm-up)")
    p.add_argument("--publish-every", type=int, default=env_default("publish_every", 50), help="learner: updates per broadcast")
    p.add_argument("--export-every-s", type=float, default=env_default("export_every_s", 60.0))
    p.add_argument("--checkpoint-every-s", type=float, default=env_default("checkpoint_every_s", 60.0))
    p.add_argument("--threads", type=int, default=env_default("threads", 1), help="learner: torch threads")
    p.add_argument("--router-timeout-s", type=float, default=env_default("router_timeout_s", 60.0),
                   help="give up (exit 2) when the router does not answer within this at start; -1 waits forever")
    add_config_arguments(p)
    p.add_argument("--world", default=None, help="world to train on (curriculum.world; CURLNAV_WORLD)")
    p.add_argument("--curriculum", default=None, help="curriculum YAML (curriculum.file; CURLNAV_CURRICULUM)")


def build_service(args):
    """The service object of ``args.role`` (not yet running): its experiment config resolved and
    validated, its worlds and curriculum loaded. Raises on any bad input, before any network."""
    import zlib

    from .experiment_cli import experiment_from_args
    from .service import Deployment
    from .sim import get_world

    experiment = experiment_from_args(args)
    get_world(experiment.curriculum.world)  # an unknown world fails here, with its name
    data = Path(args.data_dir)

    def deployment(folder: str, default_port: int = 0) -> Deployment:
        return Deployment(run=args.run, router=args.router, data_dir=str(data / folder) if folder else "",
                          http_port=args.http_port or default_port)

    if args.role == "replay":
        from curlnav.replay.service import ReplayService, ReplayServiceConfig

        return ReplayService(ReplayServiceConfig(deployment("replay")), experiment)
    if args.role == "learner":
        from curlnav.learner.service import LearnerService, LearnerServiceConfig

        return LearnerService(LearnerServiceConfig(deployment("learner"), publish_every=args.publish_every,
                                                   export_every_s=args.export_every_s,
                                                   checkpoint_every_s=args.checkpoint_every_s,
                                                   torch_threads=args.threads), experiment)
    if args.role == "scheduler":
        from curlnav.scheduler.service import SchedulerService, SchedulerServiceConfig

        service = SchedulerService(SchedulerServiceConfig(deployment("scheduler", 8080), admin_token=args.admin_token),
                                   experiment)
        for stage in service.core.curriculum.stages:
            for world in stage.worlds:
                get_world(world)
        return service
    if args.role == "actor":
        from curlnav.actor.service import ActorService, ActorServiceConfig

        actor_id = args.actor_id or f"{socket.gethostname()}-{os.getpid()}"
        index = args.actor_index if args.actor_index >= 0 else zlib.crc32(actor_id.encode()) % 997
        return ActorService(ActorServiceConfig(actor_id=actor_id, actor_index=index, actor_count=args.actor_count,
                                               deployment=deployment(f"actors/{actor_id}")), experiment)
    raise ValueError(f"no service for role {args.role!r}")


def serve(args) -> int:
    """Run one service until SIGTERM/SIGINT. Bad configuration exits with a one-line reason."""
    import curlnav.transport as transport
    from curlnav.transport import run_router, stop_on_signals

    transport.ROUTER_TIMEOUT_S = args.router_timeout_s
    logging.basicConfig(level=logging.INFO, format=f"%(asctime)s {args.role} %(levelname)s %(message)s")
    stop = threading.Event()
    stop_on_signals(stop)
    if args.role == "router":
        peers = [e.strip() for e in args.connect.split(",") if e.strip()]
        logging.info("router listening on %s%s", args.listen, f", joining {peers}" if peers else "")
        run_router(args.listen, stop, connect=peers or None)
        return 0
    service = build_service(args)
    service.stop = stop
    service.run()
    return 0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def http_json(url: str, timeout: float = 2.0):
    with urllib.request.urlopen(url, timeout=timeout) as response:
        return json.loads(response.read())


class LocalCluster:
    """Router, replay, learner, scheduler and N actors as local processes (one run folder).

    Every service reads the same experiment config, ``<run_dir>/config.yaml`` (written here
    from ``experiment``), and gets only deployment options on its command line.
    """

    def __init__(self, run_dir: str | Path, experiment=None, actors: int = 2, run: str = "local",
                 extra: dict[str, list[str]] | None = None, admin_token: str = "", learner_threads: int = 1) -> None:
        from .config import ExperimentConfig, config_to_yaml

        self.run_dir = Path(run_dir)
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        self.experiment = experiment or ExperimentConfig()
        self.config_path = self.run_dir / "config.yaml"
        self.config_path.write_text(config_to_yaml(self.experiment))
        self.router_port = free_port()
        self.scheduler_port = free_port()
        self.router = f"tcp/127.0.0.1:{self.router_port}"
        self.run, self.actors = run, actors
        self.extra = extra or {}
        self.admin_token = admin_token
        self.learner_threads = learner_threads
        self.processes: dict[str, subprocess.Popen] = {}

    def _spawn(self, name: str, role: str, *more: str) -> subprocess.Popen:
        cmd = [sys.executable, "-m", "curlnav.cli", "serve", role, "--run", self.run, "--router", self.router,
               "--listen", f"tcp/127.0.0.1:{self.router_port}", "--data-dir", str(self.run_dir),
               "--config", str(self.config_path), *self.extra.get(role, []), *more]
        log = open(self.run_dir / "logs" / f"{name}.log", "ab")
        # the services must not read the launcher's CURLNAV_* config variables: config.yaml is the config
        env = {k: v for k, v in os.environ.items() if not (k.startswith("CURLNAV_") and "__" in k)
               and k not in ("CURLNAV_PRESET", "CURLNAV_CONFIG", "CURLNAV_WORLD", "CURLNAV_CURRICULUM")}
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True, env=env)
        self.processes[name] = proc
        return proc

    def start(self) -> None:
        self._spawn("router", "router")
        self._spawn("replay", "replay")
        self._spawn("learner", "learner", "--threads", str(self.learner_threads))
        sched = ["--http-port", str(self.scheduler_port)]
        if self.admin_token:
            sched += ["--admin-token", self.admin_token]
        self._spawn("scheduler", "scheduler", *sched)
        for i in range(self.actors):
            self.start_actor(i)

    def start_actor(self, i: int) -> subprocess.Popen:
        return self._spawn(f"actor-{i}", "actor", "--actor-id", f"actor-{i}", "--actor-index", str(i),
                           "--actor-count", str(self.actors))

    @property
    def status_url(self) -> str:
        return f"http://127.0.0.1:{self.scheduler_port}/status"

    def status(self) -> dict | None:
        try:
            return http_json(self.status_url)
        except OSError:
            return None

    def learner_port(self) -> int | None:
        path = self.run_dir / "learner" / "http_port"
        return int(path.read_text()) if path.exists() else None

    def dead(self) -> list[str]:
        return [name for name, p in self.processes.items() if p.poll() is not None]

    def stop_process(self, name: str, timeout: float = 30.0) -> None:
        proc = self.processes.pop(name)
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()

    def kill_process(self, name: str) -> None:
        proc = self.processes.pop(name)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()

    def stop(self) -> None:
        order = [n for n in self.processes if n.startswith("actor")] + ["learner", "replay", "scheduler", "router"]
        for name in order:
            if name in self.processes:
                self.stop_process(name)

    def __enter__(self) -> "LocalCluster":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def train_embedded(run_dir: str | Path, experiment, actors: int, learner_threads: int = 1) -> dict:
    """``curlnav train``: the services as local processes, progress every 5 s, the evaluation
    protocol on the learner's latest artefact, clean shutdown on Ctrl-C, SIGTERM or the budget
    (``budget.minutes`` or ``budget.max_env_steps`` transitions inserted in the replay)."""
    from curlnav.evaluate import EvaluationProtocol
    from curlnav.policy import PolicyArtefact

    run_dir = Path(run_dir)
    cluster = LocalCluster(run_dir, experiment, actors=actors, learner_threads=learner_threads)
    evals: list[dict] = []
    budget, evaluation = experiment.budget, experiment.evaluation
    protocol = EvaluationProtocol(experiment) if not experiment.curriculum.file else None
    start = time.monotonic()

    def on_term(signum, frame):
        raise KeyboardInterrupt  # SIGTERM stops the run as cleanly as Ctrl-C

    signal.signal(signal.SIGTERM, on_term)
    cluster.start()
    print(f"services started: router {cluster.router}, scheduler {cluster.status_url}, logs in {run_dir / 'logs'}")
    last_eval = time.monotonic()
    stop_reason = "time budget"
    try:
        while time.monotonic() - start < budget.minutes * 60:
            time.sleep(5.0)
            dead = cluster.dead()
            if dead:
                stop_reason = f"service exited: {', '.join(dead)} (see {run_dir / 'logs'})"
                break
            s = cluster.status()
            if s:
                rate = s["success_last_100"]
                replay, learner = s["replay"], s["learner"]
                print(f"[{(time.monotonic() - start) / 60:5.1f} min] stage {s['stage']} sub-step {s['substep']} "
                      f"episodes {s['episodes']} success {'-' if rate is None else f'{rate:.0%}'} "
                      f"env steps/s {replay.get('insert_rate') or 0:.0f} updates/s {learner.get('updates_per_s') or 0:.1f} "
                      f"learner v{learner.get('version')} replay {replay.get('size')} actors {len(s['live_actors'])}",
                      flush=True)
                if budget.max_env_steps is not None and (replay.get("inserted") or 0) >= budget.max_env_steps:
                    stop_reason = "env step budget"
                    break
            port = cluster.learner_port()
            if protocol and port and time.monotonic() - last_eval >= evaluation.every_s:
                last_eval = time.monotonic()
                folder = _download_latest(port, run_dir / "eval-policy")
                if folder:
                    result = protocol.run(PolicyArtefact(folder))
                    row = {"wall_s": time.monotonic() - start, "version": PolicyArtefact(folder).version,
                           **{k: getattr(result, k) for k in ("success_rate", "collisions_per_episode", "mean_time_to_goal_s")}}
                    evals.append(row)
                    print(f"[eval {row['wall_s'] / 60:5.1f} min, policy v{row['version']}] {result.line()}", flush=True)
                    if evaluation.stop_at_success is not None and result.success_rate >= evaluation.stop_at_success:
                        stop_reason = f"held-out success {result.success_rate:.0%}"
                        break
    except KeyboardInterrupt:
        stop_reason = "interrupted"
    finally:
        print("stopping services (checkpoints and replay are saved)...", flush=True)
        cluster.stop()
        if protocol:
            protocol.close()
    summary = {"stop_reason": stop_reason, "wall_s": time.monotonic() - start, "evals": evals,
               "first_eval_reaching_80": next((e for e in evals if e["success_rate"] >= 0.8), None),
               "run_dir": str(run_dir)}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def _download_latest(port: int, out: Path) -> Path | None:
    """Fetch the learner's latest artefact over HTTP into ``out`` (sha256 checked on load)."""
    from curlnav.pull import pull_policy

    try:
        return pull_policy(f"http://127.0.0.1:{port}", out)
    except (OSError, ValueError):
        return None
