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

from curlnav.bus.commands import env_default

ROLES = ("router", "replay", "learner", "scheduler", "actor")


def add_serve_arguments(p) -> None:
    """``curlnav serve ROLE``: deployment options, plus the experiment config (``--preset``,
    ``--config``, ``--set``, ``--world``, ``--curriculum``), which every service of a run must share."""
    from curlnav.run.options import add_config_arguments

    p.add_argument("role", choices=ROLES)
    p.add_argument("--run", default=env_default("run", "default"), help="run name: the Zenoh key prefix")
    p.add_argument("--router", default=env_default("router", "tcp/127.0.0.1:7447"), help="Zenoh router endpoint")
    p.add_argument("--listen", default=env_default("listen", "tcp/0.0.0.0:7447"),
                   help="router: listen endpoints, comma-separated (tls/ADDRESS:PORT for other hosts' routers)")
    p.add_argument("--tls", default=env_default("tls", ""), metavar="NAME",
                   help="router: its name in the run's TLS folder (`curlnav bus credentials --tls NAME=ADDRESS`): "
                        "tls/ endpoints, listened on and connected to, use mutual TLS with the run's CA")
    p.add_argument("--connect", default=env_default("connect", ""),
                   help="router: other routers to join, comma-separated endpoints (multi-host)")
    p.add_argument("--data-dir", default=env_default("data_dir", "runs/service"), help="state folder (per role below it)")
    p.add_argument("--http-port", type=int, default=env_default("http_port", 0))
    p.add_argument("--http-host", default=env_default("http_host", "0.0.0.0"),
                   help="HTTP bind address (containers: all interfaces; `curlnav train` passes 127.0.0.1)")
    p.add_argument("--admin-token", default=env_default("admin_token", ""), help="scheduler: admin bearer token")
    p.add_argument("--actor-id", default=env_default("actor_id", ""),
                   help="actor: id (default: an identity claimed from --bus-credentials' actor-<n> folders, else host-pid)")
    p.add_argument("--actor-slot", type=int, default=env_default("actor_slot", 0),
                   help="actor: claim identity actor-<slot-1> (Swarm: CURLNAV_ACTOR_SLOT={{.Task.Slot}}); 0: the first free")
    p.add_argument("--actor-index", type=int, default=env_default("actor_index", -1),
                   help="actor: rung of the sigma ladder and seed offset (default: from the actor id)")
    p.add_argument("--actor-count", type=int, default=env_default("actor_count", 1),
                   help="actor: actors in the run (each takes this share of the warm-up)")
    p.add_argument("--publish-every", type=int, default=env_default("publish_every", 50), help="learner: updates per broadcast")
    p.add_argument("--export-every-s", type=float, default=env_default("export_every_s", 60.0))
    p.add_argument("--checkpoint-every-s", type=float, default=env_default("checkpoint_every_s", 30.0),
                   help="learner: s between checkpoints (a crash loses at most this much learning)")
    p.add_argument("--threads", type=int, default=env_default("threads", 1), help="learner: torch threads")
    p.add_argument("--device", default=env_default("device", "auto"),
                   help="learner: auto (cuda when a GPU is present, else cpu), cuda, cuda:N or cpu")
    p.add_argument("--compile", default=env_default("compile", "off"), choices=("off", "default", "reduce-overhead"),
                   help="learner: torch.compile of the networks: off, default, reduce-overhead (CUDA graphs)")
    p.add_argument("--amp", default=env_default("amp", "off"), choices=("off", "bf16"),
                   help="learner: off or bf16 (bfloat16 autocast)")
    p.add_argument("--shm", action="store_true", default=bool(env_default("shm", "")),
                   help="replay: answer samples through Zenoh shared memory (a learner on the same host)")
    p.add_argument("--bus-credentials", default=env_default("bus_credentials", ""),
                   help="the run's bus credentials folder (`curlnav bus credentials`) or this role's own: "
                        "services authenticate as their role, the router admits only the run's users and "
                        "applies its access control (default: none, an open bus)")
    p.add_argument("--router-timeout-s", type=float, default=env_default("router_timeout_s", 60.0),
                   help="give up (exit 2) when the router does not answer within this at start; -1 waits forever")
    add_config_arguments(p)
    p.add_argument("--world", default=None, help="world to train on: built-in name, world YAML or FAMILY:SEED "
                                                 "(curriculum.world; CURLNAV_WORLD)")
    p.add_argument("--curriculum", default=None, help="curriculum YAML (curriculum.file; CURLNAV_CURRICULUM)")


def build_service(args):
    """The service object of ``args.role`` (not yet running): its experiment config resolved and
    validated, its worlds and curriculum loaded. Raises on any bad input, before any network."""
    import zlib

    from curlnav.builder import D4PGBuilder
    from curlnav.bus.service import Deployment
    from curlnav.run.options import experiment_from_args
    from curlnav.sim import get_world

    experiment = experiment_from_args(args)
    get_world(experiment.curriculum.world)  # an unknown world fails here, with its name
    data = Path(args.data_dir)

    def deployment(folder: str, default_port: int = 0) -> Deployment:
        return Deployment(run=args.run, router=args.router, data_dir=str(data / folder) if folder else "",
                          http_host=args.http_host, http_port=args.http_port or default_port,
                          credentials=args.bus_credentials)

    if args.role == "replay":
        from curlnav.replay.service import ReplayServiceConfig

        return D4PGBuilder(experiment).make_replay_service(ReplayServiceConfig(deployment("replay"), shm=args.shm))
    if args.role == "learner":
        from curlnav.learner.service import LearnerServiceConfig

        return D4PGBuilder(experiment).make_learner_service(
            LearnerServiceConfig(deployment("learner"), publish_every=args.publish_every,
                                 export_every_s=args.export_every_s, checkpoint_every_s=args.checkpoint_every_s,
                                 torch_threads=args.threads, device=args.device, compile=args.compile,
                                 amp=args.amp))
    if args.role == "scheduler":
        from curlnav.scheduler.service import SchedulerService, SchedulerServiceConfig

        service = SchedulerService(SchedulerServiceConfig(deployment("scheduler", 8080), admin_token=args.admin_token),
                                   experiment)
        from curlnav.scheduler.curriculum import check_curriculum

        check_curriculum(service.core.curriculum, experiment.curriculum.file)
        return service
    if args.role == "actor":
        from curlnav.actor.service import ActorServiceConfig

        actor_id, claimed = _actor_identity(args)
        index = args.actor_index if args.actor_index >= 0 else claimed if claimed is not None \
            else zlib.crc32(actor_id.encode()) % 997
        return D4PGBuilder(experiment).make_actor_service(
            ActorServiceConfig(actor_id=actor_id, actor_index=index, actor_count=args.actor_count,
                               envs=experiment.actor.envs_per_process, deployment=deployment(f"actors/{actor_id}")))
    raise ValueError(f"no service for role {args.role!r}")


def _actor_identity(args) -> tuple[str, int | None]:
    """The actor's id, and the number n of the identity ``actor-<n>`` it claimed (None if none):
    ``--actor-id``; else the one actor of a folder of one actor's credentials; else, from a folder
    of actor identities (compose's ``bus-actors`` volume, Swarm's secrets), one claimed for this
    process's life (``--actor-slot``'s, or the first free: ``curlnav.bus.identity``); else host-pid
    (no credentials, or only the shared actor user of ``--shared-actor``). An id named either way
    takes the lock a claim takes (``hold_actor_identity``): refused while another process holds it."""
    from curlnav.bus.identity import actor_identities, claim_actor_identity, hold_actor_identity

    own = args.actor_id or _credentials_actor_id(args.bus_credentials)
    if own:
        if args.bus_credentials:
            hold_actor_identity(args.bus_credentials, own)
        return own, None
    if args.bus_credentials and (args.actor_slot or actor_identities(args.bus_credentials)):
        claim = claim_actor_identity(args.bus_credentials, args.actor_slot or None)
        logging.info("actor: claimed bus identity %s in %s", claim.name, claim.folder.parent)
        return claim.name, claim.index
    if args.actor_slot:
        return f"actor-{args.actor_slot - 1}", args.actor_slot - 1
    return f"{socket.gethostname()}-{os.getpid()}", None


def _credentials_actor_id(credentials: str) -> str:
    """An actor given only its own credentials folder (``DIR/actor-<n>``) is that actor."""
    if not credentials or not (Path(credentials) / "user.json").is_file():
        return ""
    from curlnav.bus.security import SHARED_ACTOR, load_user

    user = load_user(credentials, "actor")
    return "" if user.user == SHARED_ACTOR else user.user


def serve(args) -> int:
    """Run one service until SIGTERM/SIGINT. Bad configuration exits with a one-line reason."""
    import curlnav.bus.transport as transport
    from curlnav.bus.transport import run_router, stop_on_signals

    transport.ROUTER_TIMEOUT_S = args.router_timeout_s
    logging.basicConfig(level=logging.INFO, format=f"%(asctime)s {args.role} %(levelname)s %(message)s")
    stop = threading.Event()
    stop_on_signals(stop)
    die_with_launcher()
    if args.role == "router":
        peers = [e.strip() for e in args.connect.split(",") if e.strip()]
        logging.info("router listening on %s%s", args.listen, f", joining {peers}" if peers else "")
        listen = [e.strip() for e in args.listen.split(",") if e.strip()]
        run_router(listen, stop, connect=peers or None, credentials=args.bus_credentials, tls_name=args.tls)
        return 0
    service = build_service(args)  # bad input raises here: one line, exit 2 (refused)
    service.stop = stop
    try:
        service.run()
    except REFUSALS:
        raise  # the run's config, credentials or router refused at start: exit 2
    except (ValueError, KeyError) as exc:  # anything else while running is a failure, not a refusal
        logging.exception("%s failed: %s", args.role, exc)
        return 1
    return 0


def _refusals() -> tuple[type, ...]:
    from curlnav.bus.security import BusCredentialsError
    from curlnav.bus.service import ConfigMismatch
    from curlnav.bus.transport import RouterUnreachable
    from curlnav.config import ConfigError

    return ConfigError, ConfigMismatch, RouterUnreachable, BusCredentialsError


REFUSALS = _refusals()


def shell_command(program: str, *args: str) -> str:
    """``program args`` as a line that works typed in a shell where the virtual environment is
    not activated: ``program`` by the absolute path of the console script beside the running
    interpreter (``.venv/bin/curlnav``); without one, ``curlnav`` runs as ``python -m curlnav.cli``
    and ``tensorboard`` as ``python -m tensorboard.main`` (same interpreter)."""
    import shlex

    script = Path(sys.executable).absolute().parent / program
    if script.is_file() and os.access(script, os.X_OK):
        head = [str(script)]
    else:
        module = {"curlnav": "curlnav.cli", "tensorboard": "tensorboard.main"}.get(program)
        head = [sys.executable, "-m", module] if module else [program]
    return shlex.join([*head, *(str(a) for a in args)])


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def http_json(url: str, timeout: float = 2.0):
    with urllib.request.urlopen(url, timeout=timeout) as response:
        return json.loads(response.read())


def http_json_or_none(url: str, timeout: float = 3.0):
    """``http_json``, or None when the service does not answer (yet) or answers garbage."""
    try:
        return http_json(url, timeout)
    except (OSError, ValueError):
        return None


LAUNCHER_PID_VARIABLE = "CURLNAV_LAUNCHER_PID"


def die_with_launcher() -> None:
    """In a service started by ``LocalCluster``: get SIGTERM when the launcher dies, even by
    SIGKILL (Linux ``PR_SET_PDEATHSIG``), so a killed launcher leaves no orphan behind. Called
    by the service itself at start (never in a ``preexec_fn``: the launcher has threads)."""
    launcher = os.environ.get(LAUNCHER_PID_VARIABLE)
    if not launcher or not sys.platform.startswith("linux"):
        return
    import ctypes

    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    if os.getppid() != int(launcher):  # the launcher died before prctl took effect
        os.kill(os.getpid(), signal.SIGTERM)


#: the order in which a cluster stops: actors and the evaluator first, the router last
STOP_ORDER = ("actor", "evaluator", "learner", "replay", "scheduler", "router")


class LocalCluster:
    """Router, replay, learner, scheduler and N actors as local processes (one run folder).

    Every service reads the same experiment config, ``<run_dir>/config.yaml`` (written here
    from ``experiment``), and gets only deployment options on its command line. The services
    form one process group of their own (so a terminal's Ctrl-C or hang-up reaches only the
    launcher, which stops them in order), and each gets SIGTERM if the launcher dies.
    """

    def __init__(self, run_dir: str | Path, experiment=None, actors: int = 2, run: str = "local",
                 extra: dict[str, list[str]] | None = None, admin_token: str = "", learner_threads: int = 1,
                 scheduler_port: int | None = None, learner_port: int | None = None) -> None:
        from curlnav.config import ExperimentConfig, config_to_yaml

        self.run_dir = Path(run_dir)
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        self.experiment = experiment or ExperimentConfig()
        self.config_path = self.run_dir / "config.yaml"
        self.config_path.write_text(config_to_yaml(self.experiment))
        self.router_port = free_port()
        self.scheduler_port = scheduler_port or free_port()
        self.learner_http_port = learner_port or free_port()
        self.router = f"tcp/127.0.0.1:{self.router_port}"
        # the bus credentials of the run: made once, kept across --resume; each service is given
        # only its own folder (``credentials``), so an actor holds its own password alone
        from curlnav.bus.security import make_credentials

        self.bus_dir = self.run_dir / "bus"
        make_credentials(self.bus_dir, run, actors=max(actors, 1))
        self.run, self.actors = run, actors
        self.extra = extra or {}
        self.admin_token = admin_token
        self.learner_threads = learner_threads
        self.processes: dict[str, subprocess.Popen] = {}
        self.stop_report: list[tuple[str, float, bool]] = []  # (service, s from SIGTERM to exit, killed)
        self.service_env: dict[str, dict[str, str]] = {}  # name -> extra environment (secrets)
        self.commands: dict[str, list[str]] = {}  # name -> command line (a restart runs the same)
        self.pgid: int | None = None  # the services' process group

    def credentials(self, name: str) -> Path:
        """The credentials service ``name`` (a role, or an actor's ``actor-<n>``) is given: its own
        folder of the run's, ``bus/<name>`` (the router's: its dictionary and access control; an
        actor's: its ``user.json`` alone)."""
        return self.bus_dir / name

    def service_command(self, role: str, *more: str, identity: str = "") -> list[str]:
        """``curlnav serve role`` for this cluster; ``identity``: whose credentials it is given
        (an actor's ``actor-<n>``; default: the role's own, for an actor ``actor-0``'s)."""
        identity = identity or ("actor-0" if role == "actor" else role)
        return [sys.executable, "-m", "curlnav.cli", "serve", role, "--run", self.run, "--router", self.router,
                "--listen", f"tcp/127.0.0.1:{self.router_port}", "--data-dir", str(self.run_dir),
                "--http-host", "127.0.0.1", "--config", str(self.config_path),
                "--bus-credentials", str(self.credentials(identity)), *self.extra.get(role, []), *more]

    def bus_session(self, role: str, connect_timeout_s: float = 10.0, ident: str = "actor-0"):
        """A Zenoh session to this cluster's router, authenticated as ``role`` (an actor: as
        actor ``ident``) (tests, tools)."""
        from curlnav.bus.security import load_user
        from curlnav.bus.transport import open_session

        user = load_user(self.bus_dir, role, self.run, ident if role == "actor" else None)
        return open_session(self.router, connect_timeout_s, user=user)

    def _spawn(self, name: str, role: str, *more: str) -> subprocess.Popen:
        return self.spawn(name, self.service_command(role, *more, identity=name))

    def spawn(self, name: str, cmd: list[str]) -> subprocess.Popen:
        """Start ``cmd`` as service ``name`` in the services' process group, its output appended
        to ``logs/<name>.log``."""
        self.commands[name] = list(cmd)
        # the services must not read the launcher's CURLNAV_* config variables: config.yaml is the config
        from curlnav.config import ENV_ALIASES

        env = {k: v for k, v in os.environ.items() if not (k.startswith("CURLNAV_") and "__" in k)
               and k not in ("CURLNAV_PRESET", "CURLNAV_CONFIG", *ENV_ALIASES)}
        with open(self.run_dir / "logs" / f"{name}.log", "ab") as log:
            log.write(f"--- {time.strftime('%Y-%m-%d %H:%M:%S')} start: {' '.join(cmd[2:])}\n".encode())
            log.flush()
            env[LAUNCHER_PID_VARIABLE] = str(os.getpid())
            env.update(self.service_env.get(name, {}))
            kwargs = dict(stdout=log, stderr=subprocess.STDOUT, env=env, stdin=subprocess.DEVNULL)
            try:
                proc = subprocess.Popen(cmd, process_group=self.pgid or 0, **kwargs)
            except (PermissionError, ProcessLookupError, subprocess.SubprocessError):
                proc = subprocess.Popen(cmd, process_group=0, **kwargs)  # every old member is gone
                self.pgid = None
        if self.pgid is None:
            self.pgid = proc.pid
        self.processes[name] = proc
        return proc

    def restart(self, name: str) -> subprocess.Popen:
        """Start service ``name`` again with the command line it had."""
        self.processes.pop(name, None)
        return self.spawn(name, self.commands[name])

    def start(self) -> None:
        self._spawn("router", "router")
        self._spawn("replay", "replay")
        self._spawn("learner", "learner", "--threads", str(self.learner_threads),
                    "--http-port", str(self.learner_http_port))
        sched = ["--http-port", str(self.scheduler_port)]
        if self.admin_token:  # in its environment, not on a command line that ps and the log show
            self.service_env["scheduler"] = {"CURLNAV_ADMIN_TOKEN": self.admin_token}
        self._spawn("scheduler", "scheduler", *sched)
        for i in range(self.actors):
            self.start_actor(i)

    def start_actor(self, i: int) -> subprocess.Popen:
        return self._spawn(f"actor-{i}", "actor", "--actor-id", f"actor-{i}", "--actor-index", str(i),
                           "--actor-count", str(self.actors))

    @property
    def status_url(self) -> str:
        return f"http://127.0.0.1:{self.scheduler_port}/status"

    @property
    def learner_url(self) -> str:
        return f"http://127.0.0.1:{self.learner_http_port}"

    def status(self) -> dict | None:
        return http_json_or_none(self.status_url, timeout=2.0)

    def learner_port(self) -> int | None:
        return self.learner_http_port

    def dead(self) -> list[str]:
        return [name for name, p in self.processes.items() if p.poll() is not None]

    def reap(self) -> list[tuple[str, int]]:
        """The services that have exited since the last call, with their exit codes (removed
        from ``processes``; ``restart(name)`` starts one again)."""
        out = []
        for name in self.dead():
            out.append((name, self.processes.pop(name).returncode))
        return out

    def log_tail(self, name: str, lines: int = 12) -> list[str]:
        path = self.run_dir / "logs" / f"{name}.log"
        try:
            with open(path, "rb") as f:
                f.seek(max(0, os.path.getsize(path) - 16384))
                return f.read().decode(errors="replace").splitlines()[-lines:]
        except OSError:
            return []

    def stop_process(self, name: str, timeout: float = 30.0) -> None:
        self._stop_all([name], timeout)

    def _stop_all(self, names: list[str], timeout: float) -> None:
        """SIGTERM to ``names`` together, then wait for each (SIGKILL after ``timeout``); each
        stop's seconds and whether it had to be killed go to ``stop_report``."""
        procs = [(n, self.processes.pop(n)) for n in names if n in self.processes]
        started = time.monotonic()
        for _, proc in procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        deadline = started + timeout
        for name, proc in procs:
            killed = False
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
                killed = True
            self.stop_report.append((name, time.monotonic() - started, killed))

    def kill_process(self, name: str) -> None:
        proc = self.processes.pop(name)
        proc.kill()
        proc.wait()

    def stop(self, timeout: float = 30.0) -> None:
        """Stop every service, in ``STOP_ORDER`` (actors together), then make sure nothing of
        the process group is left."""
        self.stop_report = []
        for role in STOP_ORDER:
            self._stop_all([n for n in list(self.processes) if n.split("-")[0] == role], timeout)
        self._stop_all(list(self.processes), timeout)
        if self.pgid is not None:
            try:
                os.killpg(self.pgid, signal.SIGKILL)  # a grandchild a service left behind
            except (ProcessLookupError, PermissionError):
                pass

    def __enter__(self) -> LocalCluster:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
