"""What the test files share: waiting, ports, curlnav processes, small replay data, markers.

Plain helpers are imported by name (``from conftest import wait_for``: the same module object
pytest loads, under its default ``prepend`` import mode); fixtures are found by pytest itself.
A test that uses the ``curlnav_proc`` fixture starts processes and opens sockets: it is marked
``slow`` and ``net`` here (``pytest -m "not slow"`` is the quick loop).
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from types import SimpleNamespace as ns

import numpy as np
import pytest

from curlnav.config import resolve_config
from curlnav.layout import ObservationLayout

ROOT = Path(__file__).resolve().parent.parent


# -- small worlds ----------------------------------------------------------------------------------
def walled_room(width: float, height: float, res: float = 0.1) -> np.ndarray:
    """An occupancy grid (m, ``res`` m cells) of an empty room walled two cells thick."""
    grid = np.zeros((int(round(height / res)), int(round(width / res))), dtype=bool)
    grid[:2], grid[-2:], grid[:, :2], grid[:, -2:] = True, True, True, True
    return grid


def fill(grid: np.ndarray, x0: float, y0: float, x1: float, y1: float, res: float = 0.1) -> None:
    """Block the rectangle ``[x0, x1) x [y0, y1)`` (m) of ``grid``."""
    grid[int(round(y0 / res)):int(round(y1 / res)), int(round(x0 / res)):int(round(x1 / res))] = True


def u_trap_world():
    """A 16 m x 10 m room; between start and goal a U of walls 4 m deep opens toward the start."""
    from curlnav.sim import StartGoal, World

    grid = walled_room(16.0, 10.0)
    fill(grid, 9.0, 2.0, 9.3, 8.0)  # the U's bottom, across the line from start to goal
    fill(grid, 5.0, 2.0, 9.3, 2.3)  # its arms, reaching back toward the start
    fill(grid, 5.0, 7.7, 9.3, 8.0)
    pair = StartGoal("through-the-u", 2.5, 5.0, 0.0, 13.0, 5.0)
    return World(name="u-trap", occupancy=grid, resolution=0.1, pairs=(pair,))


class GoalSeeker:
    """A policy with no sense of obstacles: full speed at the goal of its observation, turning
    toward it (``[v, w, 0]``, fractions); counts its calls."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        from curlnav.nav.geometry import goal_in_robot_frame

        self.calls += 1
        gx, gy = goal_in_robot_frame(observation[-3:])
        bearing = math.atan2(gy, gx)
        return np.array([1.0 if abs(bearing) < 0.5 else 0.2, float(np.clip(2.0 * bearing, -1, 1)), 0.0], np.float32)


def run_pairs(agent, world, cfg):
    """``evaluate`` ``agent`` on every pair of ``world`` (a ``World``) in an environment of its own."""
    from curlnav.evaluation.protocol import evaluate
    from curlnav.sim import NamoEnv

    env = NamoEnv(world, cfg)
    try:
        return evaluate(agent, world, list(world.pairs), cfg, env=env)
    finally:
        env.close()


# -- waiting ---------------------------------------------------------------------------------------
@pytest.fixture
def make_env():
    """``make_env(world="namo-office:3", noise=None, **env_config_fields)``: a ``NamoEnv`` with those
    senses (exact by default), collisions counted without ending the episode; all closed at the end."""
    from curlnav.sim import EnvConfig, NamoEnv
    from curlnav.sim.config import SensorNoiseConfig

    envs = []

    def make(world="namo-office:3", noise=None, **cfg):
        cfg.setdefault("end_on_base_collision", False)
        env = NamoEnv(world, EnvConfig(sensor_noise=noise or SensorNoiseConfig(), **cfg))
        envs.append(env)
        return env

    yield make
    for env in envs:
        env.close()


def wait_for(what: str, check, timeout: float = 120.0, procs=(), every: float = 0.5):
    """Poll ``check()`` every ``every`` s until it returns a truthy value (returned). An OSError
    (a service not listening yet) counts as a falsy value. Fails when ``timeout`` s pass (with the
    last value) or as soon as one of ``procs`` has exited (with the end of its output)."""
    deadline = time.monotonic() + timeout
    last = None
    while True:
        try:
            last = check()
        except OSError:
            last = None
        if last:
            return last
        for proc in procs:
            if proc.poll() is not None:
                pytest.fail(f"{what}: a curlnav process exited with {proc.returncode}: {output_of(proc)[-2000:]}")
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}; last value {last!r}")
        time.sleep(every)


# -- ports -----------------------------------------------------------------------------------------
def closed_port() -> int:
    """A loopback port nothing listens on (bound once, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def free_port() -> int:
    """A free TCP port (``curlnav.run.launch.free_port``)."""
    from curlnav.run.launch import free_port as pick

    return pick()


# -- curlnav processes -----------------------------------------------------------------------------
def run_curlnav(*args: str, cwd: Path | None = None, timeout: float = 180,
                limit_mb: int | None = None) -> subprocess.CompletedProcess:
    """Run ``curlnav ARGS`` to its end (output captured). With ``limit_mb`` the process's address
    space is capped (a memory bomb fails the test, not the machine) and the result also carries
    ``peak_mb`` (its VmHWM) and ``wall_s`` (its own time, start-up excluded)."""
    if limit_mb is None:
        return subprocess.run([sys.executable, "-m", "curlnav.cli", *args], capture_output=True, text=True,
                              timeout=timeout, cwd=cwd or ROOT)

    def cap():
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (limit_mb << 20, limit_mb << 20))

    result = subprocess.run([sys.executable, "-c", _MEASURED, *args], capture_output=True, text=True,
                            timeout=timeout, cwd=cwd or ROOT, preexec_fn=cap)
    figures = [line.split() for line in result.stdout.splitlines() if line.startswith("peak_rss_mb")]
    result.peak_mb, result.wall_s = (float(figures[-1][1]), float(figures[-1][3])) if figures else (float("nan"),) * 2
    return result


_MEASURED = """\
import resource, sys, time
t0 = time.monotonic()
from curlnav.cli import main
try:
    rc = main(sys.argv[1:])
finally:
    # VmHWM, not ru_maxrss: ru_maxrss outlives exec, so a child forked from a big pytest process
    # (preexec_fn forks) reported the test runner's own peak (453-527 MB late in a full run)
    hwm_kb = next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM:"))
    print("peak_rss_mb %.0f wall_s %.2f" % (hwm_kb / 1024, time.monotonic() - t0))
sys.exit(rc)
"""


MEMORY_CAP = 3 << 30  # address space of a CLI subprocess: a bomb fails the test instead of the machine


def run_capped(*args: str, timeout: float = 120) -> tuple[subprocess.CompletedProcess, float, float]:
    """Run the CLI under the memory cap: (result, peak RSS in MB, wall s inside the process)."""
    result = run_curlnav(*args, timeout=timeout, limit_mb=MEMORY_CAP >> 20)
    return result, result.peak_mb, result.wall_s


def assert_one_line_error(result: subprocess.CompletedProcess, *fragments: str, max_len: int = 600) -> str:
    """Exit 2, no traceback, one ``curlnav: error:`` line of at most ``max_len`` characters holding
    every fragment; returns the line."""
    assert result.returncode == 2, (result.returncode, result.stderr[-1500:])
    assert "Traceback" not in result.stderr, result.stderr[-1500:]
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("curlnav: error: "), result.stderr[:1500]
    assert len(lines[0]) <= max_len, f"{len(lines[0])} characters: {lines[0][:300]}"
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    return lines[0]


def die_with_parent() -> None:
    """SIGTERM the child when the test process dies, even by a crash that skips the teardown (Linux)."""
    if sys.platform.startswith("linux"):
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


@pytest.fixture
def curlnav_proc(tmp_path):
    """``curlnav_proc(*args)`` starts ``curlnav ARGS`` (output to a file: ``output_of``); all are
    ended (SIGTERM, then SIGKILL) when the test ends."""
    procs = []

    def start(*args: str) -> subprocess.Popen:
        log = open(tmp_path / f"proc{len(procs)}.log", "w+")
        proc = subprocess.Popen([sys.executable, "-m", "curlnav.cli", *args], cwd=ROOT, stdout=log,
                                stderr=subprocess.STDOUT, text=True, preexec_fn=die_with_parent)
        proc.log = log
        proc.stderr = log
        procs.append(proc)
        return proc

    yield start
    stop_all(procs)
    for proc in procs:
        proc.log.close()


def stop_all(procs) -> None:
    """SIGTERM to every process still running, then wait for each (SIGKILL after 10 s)."""
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
    for proc in procs:
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def output_of(proc: subprocess.Popen) -> str:
    """What a process of ``curlnav_proc`` wrote so far (else its stderr, if it was piped)."""
    log = getattr(proc, "log", None)
    if log is None:
        return proc.stderr.read() if proc.stderr else ""
    log.flush()
    log.seek(0)
    return log.read()


def stop(proc: subprocess.Popen) -> str:
    proc.terminate()
    proc.wait(15)
    return output_of(proc)


def metrics(url: str) -> dict[str, float]:
    """A Prometheus ``/metrics`` page: series (with its labels) -> value."""
    text = urllib.request.urlopen(url, timeout=3).read().decode()
    out = {}
    for line in text.splitlines():
        m = re.match(r"^([a-zA-Z_:][\w:]*(?:\{[^}]*\})?) (\S+)$", line)
        if m:
            out[m.group(1)] = float(m.group(2))
    return out


def pytest_collection_modifyitems(items):
    for item in items:
        if "curlnav_proc" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.slow)
            item.add_marker(pytest.mark.net)
        if item.get_closest_marker("benchmark"):  # `-m "not slow"` replaces addopts' `-m 'not benchmark'`
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="module")
def artefact(tmp_path_factory) -> Path:
    """A freshly exported (untrained) policy artefact, one per test module (a loaded artefact's first-action
    check is cached by its sha256: a module that counts checks needs one no other module loaded)."""
    from curlnav.config import D4PGConfig
    from curlnav.learner.artefact import export_policy
    from curlnav.learner.d4pg import init_state
    from curlnav.sim import EnvConfig

    state = init_state(D4PGConfig(seed=1), ObservationLayout.from_env_config(EnvConfig()), "cpu")
    return export_policy(state, tmp_path_factory.mktemp("artefact") / "policy", EnvConfig(), worlds=["open-room"])


# -- a learner that lies (curlnav pull) -------------------------------------------------------------
class HostileLearner:
    """An ``http.server`` on loopback serving whatever ``routes`` says: path -> (status, headers,
    body bytes or a callable writing to the socket file)."""

    def __init__(self) -> None:
        self.routes: dict[str, tuple] = {}
        routes = self.routes

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):
                entry = routes.get(self.path.split("?", 1)[0])
                if entry is None:
                    self.send_response(404)
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                status, headers, body = entry
                self.send_response(status)
                for key, value in headers.items():
                    self.send_header(key, value)
                if isinstance(body, bytes) and "Content-Length" not in headers:
                    self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                try:
                    body(self.wfile) if callable(body) else self.wfile.write(body)
                except OSError:
                    pass

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def serve_artefact(self, folder: Path, version: int = 7, extra: dict[str, bytes] | None = None,
                       listing_changes=None) -> dict:
        """List the artefact of ``folder`` (plus ``extra`` files) as the learner does; returns the listing."""
        meta = json.loads((folder / "metadata.json").read_text())
        files = {}
        contents = {p.name: p.read_bytes() for p in folder.iterdir()} | (extra or {})
        for name, data in contents.items():
            url = f"/files/{len(files)}"
            self.routes[url] = (200, {}, data)
            files[name] = {"sha256": hashlib.sha256(data).hexdigest(), "url": url}
        listing = {"version": version, "files": files, "metadata": meta}
        if listing_changes:
            listing_changes(listing)
        self.routes["/policy/latest"] = (200, {"Content-Type": "application/json"}, json.dumps(listing).encode())
        return listing

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def learner():
    server = HostileLearner()
    yield server
    server.close()


# -- episodes ---------------------------------------------------------------------------------------
def episode_loop(world, draws):
    """A 3-step episode loop on ``world`` with random actions, drawing worlds with ``draws``."""
    from curlnav.actor.loop import EpisodeLoop
    from curlnav.replay.nstep import NStepWriter
    from curlnav.sim import EnvConfig, NamoEnv

    cfg = EnvConfig(max_episode_steps=3, end_on_base_collision=False)
    rng = np.random.default_rng(0)
    return EpisodeLoop(NamoEnv(world, cfg), lambda obs: rng.uniform([0, -1, 0], [1, 1, 1]).astype(np.float32),
                       NStepWriter(ObservationLayout.from_env_config(cfg), 5, 0.99), draws)


def one_episode(loop, seed: int, world: str) -> str:
    """Runs one episode of ``loop`` on ``world`` (a distribution draws it); returns the world's name."""
    loop.begin(seed, {"world": world})
    while loop.step() is None:
        pass
    loop.flush()
    return loop.env.world.name


# -- the ROS 2 node's core: messages as plain objects (it takes any object with the fields) ----------
def scan_of(ranges, labels=None, frame="base_link", fov=math.radians(240), angle_min=None, range_max=10.0):
    n = len(ranges)
    a0 = -fov / 2 if angle_min is None else angle_min
    return ns(header=ns(frame_id=frame), angle_min=a0, angle_max=a0 + fov, angle_increment=fov / max(n - 1, 1),
              range_max=range_max, ranges=list(ranges), intensities=list(labels if labels is not None else [0.0] * n))


def odom_of(x, y, yaw=0.0, stamp_s=None, frame="odom"):
    stamp = None if stamp_s is None else ns(sec=int(stamp_s), nanosec=int(round((stamp_s % 1) * 1e9)))
    return ns(header=ns(frame_id=frame, stamp=stamp),
              pose=ns(pose=ns(position=ns(x=x, y=y), orientation=ns(x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                                    w=math.cos(yaw / 2)))))


def goal_of(x, y, frame="odom"):
    return ns(header=ns(frame_id=frame), pose=ns(position=ns(x=x, y=y)))


def step(node, t, pose, ranges=5.0, source=None):
    """One control step of the core at time ``t`` with the robot at ``pose``."""
    if source is None:
        node.on_odom(odom_of(*pose, stamp_s=1000.0 + t), t)
    else:  # the DDS publication the odometry came from
        node.on_odom(odom_of(*pose, stamp_s=1000.0 + t), t, source=source)
    node.on_scan(scan_of([ranges] * 241), t)
    return node.act(t)


# -- scheduler and hosts --------------------------------------------------------------------------
SCHEDULER_CURRICULUM = """name: t
stages:
  - name: S1
    worlds: [open-room]
    advance: {success_rate: 0.99, window: 1000}
"""


def scheduler_core(tmp_path):
    """A scheduler core on a one-stage curriculum of open-room that never advances."""
    from curlnav.scheduler.curriculum import load_curriculum
    from curlnav.scheduler.service import SchedulerCore

    path = tmp_path / "c.yaml"
    path.write_text(SCHEDULER_CURRICULUM)
    return SchedulerCore(load_curriculum(path))


def play(core, actor: str, success=True):
    """``actor`` asks ``core`` for an assignment and reports one episode of it; returns the assignment."""
    from curlnav.proto.messages import Assignment, AssignmentRequest, EpisodeReport

    a = Assignment.decode(core.assign(AssignmentRequest(actor).encode()))
    core.report(EpisodeReport(actor, a.world, a.pair, success, 1.0, 0, 0, 10, 0, a.epoch).encode())
    return a


class Namespaces:
    """The addresses and commands of ``curlnav.bench.netns.Hosts``, without namespaces."""

    count = 3

    @staticmethod
    def address(i: int) -> str:
        return f"10.9.0.{i + 1}"

    @staticmethod
    def exec(i: int) -> list[str]:
        return ["ip", "netns", "exec", f"host{i}"]


# -- replay data -----------------------------------------------------------------------------------
LAYOUT = ObservationLayout()
#: a small replay: batches of 8 from 8 transitions on, 60 held
SMALL = resolve_config(overrides=["d4pg.batch_size=8", "replay.min_size=8", "replay.capacity=60"])


def replay_in(folder: Path, experiment=SMALL):
    """A replay service on ``folder`` (not started: no bus)."""
    from curlnav.builder import D4PGBuilder
    from curlnav.bus.service import Deployment
    from curlnav.replay.service import ReplayServiceConfig

    return D4PGBuilder(experiment).make_replay_service(ReplayServiceConfig(Deployment(data_dir=str(folder))))


def a_batch(actor="a", seq=0, steps=6):
    """A ``TransitionBatch`` of one episode of ``steps`` steps (random observations, seeded by ``seq``)."""
    from curlnav.proto.messages import TransitionBatch
    from curlnav.replay.nstep import NStepWriter

    writer = NStepWriter(LAYOUT, 3, 0.9)
    rng = np.random.default_rng(seq)
    writer.first(rng.uniform(0, 10, LAYOUT.size).astype(np.float32))
    for t in range(steps):
        writer.step(np.array([0.5, 0, 0.1], np.float32), 0.1, rng.uniform(0, 10, LAYOUT.size).astype(np.float32),
                    False, t == steps - 1)
    return TransitionBatch(actor, seq, 3, writer.flush())


def random_batch(b=64, seed=0):
    """A learner ``TensorBatch`` of ``b`` random transitions of the default layout."""
    import torch

    from curlnav.learner.d4pg import TensorBatch

    g = torch.Generator().manual_seed(seed)
    return TensorBatch(torch.rand(b, LAYOUT.size, generator=g) * 5, torch.rand(b, 3, generator=g),
                       torch.randn(b, generator=g) * 10, torch.full((b,), 0.95), torch.rand(b, LAYOUT.size, generator=g) * 5)


#: a tiny layout whose frames encode (episode, step): ``obs_for`` and ``expected_stack``
REPLAY_LAYOUT = ObservationLayout(beams=5, range_frames=4, label_frames=4, goal_frames=10)


def obs_for(step: int, episode: int = 0) -> np.ndarray:
    """A stacked observation whose newest frame encodes (episode, step); the rest is ignored by
    the writer and rebuilt by the table."""
    obs = np.zeros(REPLAY_LAYOUT.size, np.float32)
    ranges, labels, goal = REPLAY_LAYOUT.newest_frame(obs)
    ranges[:] = 0.5 * step + 0.125 * np.arange(REPLAY_LAYOUT.beams) + 0.25 * episode  # exact in float16
    labels[:] = step % 2
    goal[:] = (step, -step, episode)
    return obs


def expected_stack(steps: list[int], episode: int = 0) -> np.ndarray:
    """The stacked observation after ``steps`` (first frame repeated at the episode start)."""
    def frame(k):
        return obs_for(k, episode)

    out = np.zeros(REPLAY_LAYOUT.size, np.float32)
    b = REPLAY_LAYOUT.beams
    hist = [steps[0]] * REPLAY_LAYOUT.history + list(steps)
    for i in range(REPLAY_LAYOUT.range_frames):
        out[i * b:(i + 1) * b] = REPLAY_LAYOUT.newest_frame(frame(hist[-REPLAY_LAYOUT.range_frames + i]))[0]
    off = REPLAY_LAYOUT.range_frames * b
    for i in range(REPLAY_LAYOUT.label_frames):
        out[off + i * b: off + (i + 1) * b] = REPLAY_LAYOUT.newest_frame(frame(hist[-REPLAY_LAYOUT.label_frames + i]))[1]
    off += REPLAY_LAYOUT.label_frames * b
    for i in range(REPLAY_LAYOUT.goal_frames):
        out[off + 3 * i: off + 3 * i + 3] = REPLAY_LAYOUT.newest_frame(frame(hist[-REPLAY_LAYOUT.goal_frames + i]))[2]
    return out


def around(suffixes: str):
    """The stack of roles ``suffixes`` (``"+rescue+shield"``) name, round a controller the caller
    holds (``curlnav.ros2.commands.deployed`` puts its own in the stack's controller's place)."""
    from curlnav.nav import parse_agent

    return parse_agent("dwa" + suffixes)
