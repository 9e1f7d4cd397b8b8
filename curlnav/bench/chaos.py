"""``curlnav bench chaos``: a long local run under chaos, and what it lost.

A real local run (``LocalCluster``: router, replay, learner, scheduler and actors as processes, a
small curriculum of its own) trains while, every few tens of seconds (uniform in [every_s / 2,
3 every_s / 2]), a fault hits one service: ``kill -9`` of the router, the replay, the learner, the
scheduler or an actor, or a **stall** (``SIGSTOP`` of the router or an actor for a few seconds,
then ``SIGCONT``: a link cut, shorter or longer than Zenoh's 10 s lease). The kinds come in
shuffled rounds, so every kind is hit once per six faults. The bench supervises the run as
``curlnav train`` does (a service that exits is started again, here with no restart budget).

Per fault one line: what, when, seconds until the service answered again (``back``) and until the
run moved again (``moving``: transitions accepted, for the learner a new weights version, for the
scheduler an episode counted, for an actor its own transitions accepted); per minute one line
(transitions generated, accepted and dropped by the replay, learner version, curriculum stage and
epoch). At the end the actors stop gracefully (their final flush) and the bench checks:

- **lost** (transitions): what the actors generated and the replay did not store. Per actor
  process, what it generated against what the replay accepted from it. The replay's log
  (``replay/wal``, read as it grows: ``LogTally``) names each accepted batch's actor and ``seq``,
  and a process numbers its batches from its start time in microseconds, so every accepted batch
  belongs to one process. A process that stopped gracefully wrote ``actor-final.json``
  (generated, unacknowledged): lost = generated - accepted - unacknowledged. A process killed (or
  crashed) took its unacknowledged batches with it: they are **in flight**, not lost (its
  generated count is its last reading, taken just before the kill, or what was accepted from it
  if more). The replay's accepted count going back, or below what its log was seen to hold, is
  lost too; and so is every accepted transition the replay did not store (**dropped**: a frame it
  no longer knew or held), by its own count over the run (``dropped.json`` in its folder, read
  after it stopped, or the most its ``/healthz`` was seen to say, if more). So lost = generated -
  stored - in flight, not generated - accepted. ``account``.
- **versions monotonic**: the learner's weights version, sampled every second across learner
  restarts, never went back, and its version mark (``learner/version``) is at least the highest.
- **curriculum intact**: ``scheduler/state.json`` reads back, matches the scheduler's last
  status (stage, sub-step, epoch, episodes), holds every advance ever seen (epochs 1..E), and the
  stage, epoch and episodes sampled over the run never went back. ``curriculum_problems``.
- **policy intact**: every exported artefact of the learner (``learner/artefacts/v*``) has its
  files, each with the sha256 its ``metadata.json`` lists. ``artefact_problems``.

The last line::

    chaos M min: faults F (router r, replay p, learner l, scheduler s, actor a, stalls t), generated G,
    accepted N, dropped by the replay D, in flight I, lost L, versions monotonic yes, curriculum intact
    yes, policy intact yes

(D is part of L: accepted, but not stored.)

The command exits non-zero when lost > 0, a check fails, a service did not come back or an actor
did not report its final flush. The pure parts (``fault_schedule``, ``went_back``, ``account``,
``LogTally``, ``curriculum_problems``, ``artefact_problems``) need no network.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import socket
import time
import urllib.request
import zlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

FAULT_KINDS = ("router", "replay", "learner", "scheduler", "actor", "stall")
STALL_S = (3.0, 15.0)  # a stall lasts uniform in this range (s): below and beyond Zenoh's 10 s lease
MARKER = "chaos.json"  # in a run folder this bench made (it refuses to clear any other)
HELP = ("a long local run under chaos: kill -9 of a random service (router, replay, learner, scheduler, an actor) or "
        "a stall, every few tens of seconds; what was lost, whether versions, curriculum and policy stayed intact")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--minutes", type=float, required=True, metavar="M", help="minutes of chaos (after the run has started)")
    p.add_argument("--actors", type=int, default=2, metavar="N", help="actor processes")
    p.add_argument("--every-s", type=float, default=30.0, metavar="S",
                   help="mean seconds between faults (each gap uniform in [S/2, 3S/2])")
    p.add_argument("--seed", type=int, default=0, metavar="K", help="the fault schedule's and the run's seed")
    p.add_argument("--run-dir", default="runs/bench-chaos", metavar="DIR",
                   help="a new folder, or one this bench made (cleared)")


def main(args: argparse.Namespace) -> int:
    result = run_chaos_bench(args.minutes, actors=args.actors, every_s=args.every_s, seed=args.seed,
                             run_dir=args.run_dir)  # bad input: ValueError, one line, exit 2
    return 0 if result.ok else 1


# -- the pure core ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class Fault:
    """One fault: ``kind`` (``FAULT_KINDS``) on service ``target`` (``router``, ``replay``,
    ``learner``, ``scheduler``, ``actor-<i>``), ``gap_s`` seconds after the previous one was
    injected (and never before it recovered); a stall lasts ``stall_s`` seconds."""

    gap_s: float
    kind: str
    target: str
    stall_s: float = 0.0


def fault_schedule(window_s: float, every_s: float, actors: int, seed: int = 0,
                   stall_s: tuple[float, float] = STALL_S) -> list[Fault]:
    """The faults of ``window_s`` seconds of chaos: gaps uniform in [every_s / 2, 3 every_s / 2]
    (s), kinds in shuffled rounds of ``FAULT_KINDS``, an actor target uniform among ``actors``,
    a stall on the router or an actor (half each) for uniform ``stall_s`` seconds. Same seed,
    same schedule."""
    if not every_s > 0 or not window_s >= 0 or actors < 1 or not 0 < stall_s[0] <= stall_s[1]:
        raise ValueError(f"fault schedule: every_s > 0, window_s >= 0, actors >= 1 and 0 < stall low <= high, got "
                         f"every_s {every_s}, window_s {window_s}, actors {actors}, stall {stall_s}")
    rng = random.Random(seed)
    faults: list[Fault] = []
    t, round_left = 0.0, []
    while True:
        gap = rng.uniform(every_s / 2, 3 * every_s / 2)
        if t + gap > window_s:
            return faults
        t += gap
        if not round_left:
            round_left = list(FAULT_KINDS)
            rng.shuffle(round_left)
        kind = round_left.pop()
        if kind == "actor":
            faults.append(Fault(gap, kind, f"actor-{rng.randrange(actors)}"))
        elif kind == "stall":
            target = "router" if rng.random() < 0.5 else f"actor-{rng.randrange(actors)}"
            faults.append(Fault(gap, kind, target, round(rng.uniform(*stall_s), 1)))
        else:
            faults.append(Fault(gap, kind, kind))


def went_back(samples: Iterable[tuple[float, int | None]]) -> list[tuple[float, int, int]]:
    """Every sample below the highest one before it, as (time, highest before, sample); samples
    of None (the service did not answer) are skipped. Empty: the series only went forward."""
    out, highest = [], None
    for t, value in samples:
        if value is None:
            continue
        if highest is not None and value < highest:
            out.append((t, highest, value))
        highest = value if highest is None else max(highest, value)
    return out


@dataclass
class Incarnation:
    """One actor process, from its start to its kill, crash or stop (counts in transitions)."""

    actor: str  # actor id: actor-<i>
    started_us: int  # its start, s since the epoch x 1e6: its batch seqs start above it
    generated: int = 0  # put into batches: its last reading, or its final report
    accepted: int = 0  # of those, accepted by the replay (from the replay's log)
    unacknowledged: int | None = None  # held unacknowledged at its stop (actor-final.json); None: no report
    ended: str = "running"  # running, killed (by the bench), exited (by itself), stopped (its final flush)


@dataclass(frozen=True)
class Accounting:
    """``account``'s figures (transitions): generated G, accepted N (the replay's count at the end),
    in flight I (unacknowledged at a stop, or held by a killed process), lost L (of which D
    accepted but dropped by the replay, not stored)."""

    generated: int
    accepted: int
    in_flight: int
    lost: int
    accepted_went_back: int  # the replay's count at the end below the most it had been seen to accept
    dropped: int = 0  # accepted, not stored by the replay (its count over the run)


def account(incarnations: Iterable[Incarnation], accepted_total: int, accepted_seen: int = 0, dropped: int = 0,
            dropped_seen: int = 0) -> Accounting:
    """The loss arithmetic (see the module docstring). ``accepted_total``: the replay's count at
    the end; ``accepted_seen``: the most it was seen to have accepted before (its samples, or the
    transitions its log was seen to hold); ``dropped``, ``dropped_seen``: the replay's count of
    accepted transitions it did not store, at the end and the most seen before (the larger is
    lost)."""
    generated = in_flight = lost = 0
    for inc in incarnations:
        if inc.ended == "stopped" and inc.unacknowledged is not None:
            gen = inc.generated
            missing = max(0, gen - inc.accepted)
            in_flight += min(inc.unacknowledged, missing)
            lost += max(0, missing - inc.unacknowledged)
        else:  # killed or crashed: what it held unacknowledged went with it
            gen = max(inc.generated, inc.accepted)
            in_flight += gen - inc.accepted
        generated += gen
    back = max(0, accepted_seen - accepted_total)
    not_stored = max(dropped, dropped_seen)
    return Accounting(generated, accepted_total, in_flight, lost + back + not_stored, back, not_stored)


class LogTally:
    """The replay's segment log (``replay/wal.py``), read as it grows, without ever writing to it:
    each complete, checksummed record once, as (actor, seq, transitions). A record still being
    written (short, or its checksum not yet right) is read again next time; a segment that went
    before it was read to its end is named in ``missed``; ``gaps`` lists records whose first
    transition index does not follow the one before (the log's indices run on without a hole)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.offsets: dict[str, int] = {}
        self.batches: dict[str, list[tuple[int, int]]] = {}  # actor -> [(seq, transitions)], log order
        self.total = 0  # transitions in the records read
        self.end: int | None = None  # the log index after the last record read
        self.gaps: list[tuple[int, int]] = []  # (expected first index, found)
        self.unreadable = 0
        self.missed: list[str] = []

    def read(self) -> int:
        """Read what was appended since the last call; returns the records read."""
        from curlnav.replay.wal import HEADER, MAX_RECORD_BYTES

        count = 0
        segments = sorted(self.folder.glob("seg-*.log"))
        names = {p.name for p in segments}
        for name in [n for n in self.offsets if n not in names]:
            self.missed.append(name)  # pruned: only the replay's table capacity makes it do that
            self.offsets.pop(name)
        for path in segments:
            offset = self.offsets.get(path.name, 0)
            try:
                with open(path, "rb") as f:
                    f.seek(offset)
                    while True:
                        head = f.read(HEADER.size)
                        if len(head) < HEADER.size:
                            break
                        length, crc, first = HEADER.unpack(head)
                        if not 0 < length <= MAX_RECORD_BYTES:
                            break
                        payload = f.read(length)
                        if len(payload) != length or zlib.crc32(payload) != crc:
                            break
                        self._record(first, payload)
                        offset += HEADER.size + length
                        count += 1
            except FileNotFoundError:
                continue
            self.offsets[path.name] = offset
        return count

    def _record(self, first: int, payload: bytes) -> None:
        from curlnav.proto.codec import ProtoError, loads

        if self.end is not None and first != self.end:
            self.gaps.append((self.end, first))
        try:
            obj = loads(payload)
            actor, seq, n = str(obj["actor_id"]), int(obj["seq"]), int(obj["obs_id"]["shape"][0])
        except (ProtoError, KeyError, TypeError, ValueError, IndexError):
            self.unreadable += 1
            return
        self.batches.setdefault(actor, []).append((seq, n))
        self.total += n
        self.end = first + n

    def accepted(self, actor: str, from_us: int = 0, to_us: int | None = None) -> int:
        """Transitions accepted from ``actor``'s batches numbered in [from_us, to_us)."""
        return sum(n for seq, n in self.batches.get(actor, ()) if seq >= from_us and (to_us is None or seq < to_us))


def attribute(incarnations: list[Incarnation], tally: LogTally) -> int:
    """Set each incarnation's ``accepted`` from the log (a process's seqs run from its start to the
    next process's of the same actor); returns transitions the log holds from no known process."""
    known = 0
    by_actor: dict[str, list[Incarnation]] = {}
    for inc in incarnations:
        by_actor.setdefault(inc.actor, []).append(inc)
    for actor, incs in by_actor.items():
        incs.sort(key=lambda i: i.started_us)
        for inc, after in zip(incs, incs[1:] + [None]):
            inc.accepted = tally.accepted(actor, inc.started_us, after.started_us if after else None)
            known += inc.accepted
    return tally.total - known


def curriculum_problems(saved: dict | None, final: dict, samples: list[tuple[float, dict]]) -> list[str]:
    """What is wrong with the curriculum state: ``saved`` (``scheduler/state.json``, None when
    missing or unreadable) against ``final`` (the scheduler's last ``/status``) and ``samples``
    ((time, status) over the run). Empty: intact."""
    if not isinstance(saved, dict) or not isinstance(saved.get("state"), dict):
        return ["scheduler/state.json is missing or unreadable"]
    problems = []
    state = saved["state"]
    if saved.get("curriculum") != final.get("curriculum"):
        problems.append(f"state.json is of curriculum {saved.get('curriculum')!r}, the scheduler runs "
                        f"{final.get('curriculum')!r}")
    for key, status_key in (("stage", "stage_index"), ("substep", "substep"), ("epoch", "epoch"), ("episodes", "episodes")):
        if state.get(key) != final.get(status_key):
            problems.append(f"state.json {key} {state.get(key)} but the scheduler's status says {final.get(status_key)}")
    history = state.get("history") or []
    epoch = state.get("epoch") or 0
    if [h.get("epoch") for h in history] != list(range(1, epoch + 1)):
        problems.append(f"state.json epoch {epoch} but its advances are epochs {[h.get('epoch') for h in history]}")
    for key in ("stage_index", "epoch", "episodes"):
        back = went_back((t, s.get(key)) for t, s in samples)
        if back:
            t, before, after = back[0]
            problems.append(f"{key} went back from {before} to {after} at {t:.0f} s ({len(back)} times)")
    for t, s in samples:
        seen = s.get("advances") or []
        if history[:len(seen)] != seen:
            problems.append(f"an advance seen at {t:.0f} s is not in state.json: {seen[len(history):][:1] or seen[-1:]}")
            break
    most = max((s.get("episodes") or 0 for _, s in samples), default=0)
    if (state.get("episodes") or 0) < most:
        problems.append(f"state.json counts {state.get('episodes')} episodes, {most} were seen counted")
    return problems


def artefact_problems(folder: str | Path) -> tuple[list[int], list[str], list[str]]:
    """The learner's exported artefacts in ``folder``: (versions, problems, leftovers). Every
    ``v<N>`` folder must hold the files its ``metadata.json`` lists, each with that sha256;
    leftovers are other entries (an export cut short leaves its temporary folder)."""
    from curlnav.policy import ArtefactError, PolicyArtefact, sha256_of

    folder = Path(folder)
    versions, problems, leftovers = [], [], []
    for path in sorted(folder.iterdir()) if folder.is_dir() else []:
        if not (path.is_dir() and path.name[:1] == "v" and path.name[1:].isdigit()):
            leftovers.append(path.name)
            continue
        versions.append(int(path.name[1:]))
        try:
            files = PolicyArtefact.listed_files(path)
        except ArtefactError as exc:
            problems.append(str(exc))
            continue
        for name, expected in files.items():
            if not (path / name).is_file():
                problems.append(f"{path.name}: {name} is missing")
            elif sha256_of(path / name) != expected:
                problems.append(f"{path.name}: {name} does not match the sha256 in its metadata.json")
    if not versions:
        problems.append(f"no artefact in {folder}")
    return sorted(versions), problems, leftovers


def chaos_curriculum(stage_steps: int) -> str:
    """The bench's curriculum (YAML): open-room with random pairs, two sub-steps of named pairs,
    random pairs again; each step ends after ``stage_steps`` environment steps of its episodes
    (its success criterion never holds), so the run advances a few times."""
    advance = f"{{success_rate: 1.0, window: 1000, max_env_steps: {int(stage_steps)}}}"
    return (f"name: chaos\nstages:\n"
            f"  - name: C1\n    worlds: [open-room]\n    advance: {advance}\n"
            f"  - name: C2\n    worlds: [open-room]\n    substeps: [across, up]\n"
            f"    substep_advance: {advance}\n    advance: {advance}\n"
            f"  - name: C3\n    worlds: [open-room]\n")


def summary_line(minutes: float, counts: dict[str, int], acc: Accounting, checks: dict[str, bool]) -> str:
    def yes(ok: bool) -> str:
        return "yes" if ok else "NO"

    kinds = ", ".join(f"{k} {counts.get(k, 0)}" for k in FAULT_KINDS[:-1]) + f", stalls {counts.get('stall', 0)}"
    return (f"chaos {minutes:g} min: faults {sum(counts.values())} ({kinds}), generated {acc.generated}, "
            f"accepted {acc.accepted}, dropped by the replay {acc.dropped}, in flight {acc.in_flight}, lost {acc.lost}, "
            + ", ".join(f"{name} {yes(ok)}" for name, ok in checks.items()))


# -- the shell: a real run, its faults, its checks --------------------------------------------------

def _get(url: str, timeout: float = 1.0) -> bytes | None:
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            return response.read()
    except (OSError, ValueError):
        return None


def _json(url: str, timeout: float = 1.0) -> dict | None:
    body = _get(url, timeout)
    try:
        return json.loads(body) if body else None
    except ValueError:
        return None


def _metric(text: bytes | None, name: str) -> float | None:
    for line in (text or b"").decode(errors="replace").splitlines():
        if line.startswith(name + " "):
            try:
                return float(line.split()[1])
            except (IndexError, ValueError):
                return None
    return None


@dataclass
class FaultOutcome:
    """A fault as it happened: ``at_s`` s into the chaos; ``back_s`` and ``moving_s`` s from the
    kill (a stall: from ``SIGCONT``) until the service answered and the run moved again (None:
    not within the deadline)."""

    number: int
    fault: Fault
    at_s: float
    pid: int | None = None
    back_s: float | None = None
    moving_s: float | None = None
    baseline: int | None = None  # the figure that must move (accepted, version, episodes) when it came back
    injected: float = 0.0  # monotonic time of the kill (a stall: of its SIGCONT, once sent)

    @property
    def recovered(self) -> bool:
        return self.back_s is not None and self.moving_s is not None


@dataclass
class ChaosResult:
    """What ``run_chaos_bench`` measured; ``ok``: nothing lost and every check passed."""

    summary: str
    accounting: Accounting
    checks: dict[str, bool]
    faults: list[FaultOutcome]
    problems: list[str] = field(default_factory=list)
    incarnations: list[Incarnation] = field(default_factory=list)
    versions: list[tuple[float, int | None]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.accounting.lost == 0 and all(self.checks.values())


class ChaosRun:
    """The run under chaos (see the module docstring). Everything that starts processes runs on
    the calling thread: a service's parent-death signal follows the thread that started it."""

    def __init__(self, run_dir: Path, experiment, actors: int, every_s: float, seed: int, minutes: float,
                 stall_s: tuple[float, float] = STALL_S, say=print, fault_timeout_s: float = 180.0) -> None:
        from curlnav.run.launch import LocalCluster

        self.run_dir, self.actors, self.minutes, self.say = run_dir, actors, minutes, say
        self.window_s = minutes * 60
        self.schedule = fault_schedule(self.window_s, every_s, actors, seed, stall_s)
        self.fault_timeout_s = fault_timeout_s
        self.cluster = LocalCluster(run_dir, experiment, actors=actors, run="chaos", extra={
            "learner": ["--publish-every", "20", "--export-every-s", "10", "--checkpoint-every-s", "10"]})
        self.incarnations: list[Incarnation] = []
        self.tally = LogTally(run_dir / "replay" / "wal")
        self.outcomes: list[FaultOutcome] = []
        self.unplanned: list[str] = []
        self.versions: list[tuple[float, int | None]] = []
        self.accepted: list[tuple[float, int | None]] = []
        self.dropped_seen = 0  # the most the replay's /healthz said it dropped (a run's count)
        self.statuses: list[tuple[float, dict]] = []
        self.readings: dict[str, float] = {}  # actor -> last generated reading of its current process
        self.stopped: dict[int, float] = {}  # pid -> monotonic time of its SIGCONT (a stall under way)
        self.killed: set[int] = set()  # pids the bench killed
        self.started = time.monotonic()

    # -- small reads ------------------------------------------------------------------------------
    def elapsed(self) -> float:
        return time.monotonic() - self.started

    def pid(self, name: str) -> int | None:
        proc = self.cluster.processes.get(name)
        return proc.pid if proc is not None and proc.poll() is None else None

    def port_url(self, folder: str, newer_than: float = 0.0) -> str | None:
        """``http://127.0.0.1:<port>`` from ``<folder>/http_port``, if written after ``newer_than`` (time.time())."""
        path = self.run_dir / folder / "http_port"
        try:
            if path.stat().st_mtime < newer_than:
                return None
            return f"http://127.0.0.1:{int(path.read_text())}"
        except (OSError, ValueError):
            return None

    def replay_health(self) -> dict | None:
        url = self.port_url("replay")
        return _json(f"{url}/healthz") if url else None

    def learner_health(self) -> dict | None:
        return _json(f"{self.cluster.learner_url}/healthz")

    def actor_generated(self, actor: str) -> float | None:
        current = self.current(actor)
        url = self.port_url(f"actors/{actor}", current.started_us / 1e6 if current else 0.0)
        return _metric(_get(f"{url}/metrics"), "actor_transitions_generated") if url else None

    def actor_unacknowledged(self, actor: str) -> float | None:
        current = self.current(actor)
        url = self.port_url(f"actors/{actor}", current.started_us / 1e6 if current else 0.0)
        return _metric(_get(f"{url}/metrics"), "actor_batches_unacknowledged") if url else None

    def current(self, actor: str) -> Incarnation | None:
        return next((i for i in reversed(self.incarnations) if i.actor == actor), None)

    def router_answers(self) -> bool:
        try:
            with socket.create_connection(("127.0.0.1", self.cluster.router_port), timeout=0.5):
                return True
        except OSError:
            return False

    # -- start, supervise, sample -----------------------------------------------------------------
    def spawn_actor_incarnation(self, actor: str) -> None:
        self.incarnations.append(Incarnation(actor, time.time_ns() // 1000))

    def start(self, startup_s: float = 300.0) -> None:
        for i in range(self.actors):
            self.spawn_actor_incarnation(f"actor-{i}")
        self.cluster.start()
        deadline = time.monotonic() + startup_s
        while time.monotonic() < deadline:
            self.supervise()
            status = self.cluster.status() or {}
            health = self.replay_health() or {}
            if (len(status.get("live_actors") or {}) == self.actors and (health.get("accepted") or 0) > 0
                    and (self.learner_health() or {}).get("version") is not None):
                self.started = time.monotonic()
                return
            time.sleep(0.5)
        raise RuntimeError(f"the run did not start within {startup_s:.0f} s (logs in {self.run_dir / 'logs'})")

    def supervise(self) -> None:
        """Start again every service that exited (killed by the bench, or by itself)."""
        for name in self.cluster.dead():
            proc = self.cluster.processes.pop(name)
            code = proc.returncode
            inc = self.current(name) if name.startswith("actor-") else None
            if inc is not None and inc.ended == "running":
                inc.ended = "exited"
                inc.generated = int(self.readings.get(name, 0))
            if proc.pid not in self.killed:
                self.unplanned.append(f"{name} exited with code {code} at {self.elapsed():.0f} s")
                self.say(f"!! {name} exited by itself with code {code}; last line of its log: "
                         f"{(self.cluster.log_tail(name, 1) or ['-'])[-1]}")
            if inc is not None:
                self.spawn_actor_incarnation(name)
            self.cluster.restart(name)
            self.readings.pop(name, None)

    def sample(self) -> None:
        """Versions, accepted counts, the curriculum; the log; each actor's generated count."""
        now = self.elapsed()
        self.versions.append((now, (self.learner_health() or {}).get("version")))
        replay = self.replay_health() or {}
        self.accepted.append((now, replay.get("accepted")))
        self.dropped_seen = max(self.dropped_seen, int(replay.get("dropped") or 0))
        status = self.cluster.status()
        if status:
            self.statuses.append((now, {k: status.get(k) for k in ("curriculum", "stage", "stage_index", "substep",
                                                                    "epoch", "episodes", "advances")}))
            self.last_status = status
        self.tally.read()
        for i in range(self.actors):
            actor = f"actor-{i}"
            if self.pid(actor) in self.stopped:
                continue  # stalled: its HTTP server is stopped too
            value = self.actor_generated(actor)
            if value is not None:
                self.readings[actor] = value

    last_status: dict = {}

    def generated_so_far(self) -> int:
        done = sum(i.generated for i in self.incarnations if i.ended != "running")
        return done + int(sum(self.readings.get(i.actor, 0) for i in self.incarnations if i.ended == "running"))

    def progress(self) -> None:
        s = self.last_status or {}
        version = next((v for _, v in reversed(self.versions) if v is not None), None)
        accepted = next((v for _, v in reversed(self.accepted) if v is not None), None)
        self.say(f"[{self.elapsed() / 60:5.1f} min] generated {self.generated_so_far()}, accepted {accepted}, "
                 f"dropped by the replay {self.dropped_seen}, "
                 f"learner v{version}, stage {s.get('stage')} (index {s.get('stage_index')}, sub-step "
                 f"{s.get('substep')}, epoch {s.get('epoch')}), episodes {s.get('episodes')}, actors live "
                 f"{len(s.get('live_actors') or {})}/{self.actors}, faults {len(self.outcomes)}")

    # -- faults -----------------------------------------------------------------------------------
    def inject(self, fault: Fault) -> FaultOutcome | None:
        """Kill or stop ``fault.target`` (None: it is not running at this moment, so not hit)."""
        pid = self.pid(fault.target)
        if pid is None:
            self.say(f"[{self.elapsed() / 60:5.1f} min] {fault.kind} fault on {fault.target} skipped: not running")
            return None
        outcome = FaultOutcome(len(self.outcomes) + 1, fault, self.elapsed(), pid)
        self.outcomes.append(outcome)
        if fault.kind == "stall":
            os.kill(pid, signal.SIGSTOP)
            self.stopped[pid] = time.monotonic() + fault.stall_s
        else:
            if fault.kind == "actor":
                inc = self.current(fault.target)
                reading = self.actor_generated(fault.target)
                inc.generated = int(reading if reading is not None else self.readings.get(fault.target, 0))
                inc.ended = "killed"
            self.killed.add(pid)
            os.kill(pid, signal.SIGKILL)
        outcome.injected = time.monotonic()
        return outcome

    def moving_figure(self, fault: Fault) -> int | None:
        """What must grow once the service is back: accepted transitions (of the actor, for one)."""
        if fault.kind == "learner":
            return (self.learner_health() or {}).get("version")
        if fault.kind == "scheduler":
            return (self.cluster.status() or {}).get("episodes")
        if fault.target.startswith("actor-"):
            self.tally.read()
            return self.tally.accepted(fault.target)
        return (self.replay_health() or {}).get("accepted")

    def is_back(self, outcome: FaultOutcome, since: float) -> bool:
        fault = outcome.fault
        pid = self.pid(fault.target)
        if fault.kind == "stall":
            return True
        if pid is None or pid == outcome.pid:
            return False
        if fault.kind == "router":
            return self.router_answers()
        if fault.kind == "replay":
            return ((self.replay_health() or {}).get("uptime_s") or 1e9) < since
        if fault.kind == "learner":
            return ((self.learner_health() or {}).get("uptime_s") or 1e9) < since
        if fault.kind == "scheduler":
            return self.cluster.status() is not None
        url = self.port_url(f"actors/{fault.target}", time.time() - since)
        return bool(url and _json(f"{url}/healthz"))

    def step_fault(self, outcome: FaultOutcome) -> bool:
        """Advance the fault under way; True once it is over (recovered, or past its deadline)."""
        fault = outcome.fault
        now = time.monotonic()
        if fault.kind == "stall" and outcome.pid in self.stopped:
            if now < self.stopped[outcome.pid]:
                return False
            os.kill(outcome.pid, signal.SIGCONT)
            self.stopped.pop(outcome.pid)
            outcome.injected = now  # back and moving count from SIGCONT
        since = now - outcome.injected
        if outcome.back_s is None:
            if self.is_back(outcome, since):
                outcome.back_s = since
                outcome.baseline = self.moving_figure(fault)
        elif outcome.moving_s is None:
            figure = self.moving_figure(fault)
            if figure is not None and (outcome.baseline is None or figure > outcome.baseline):
                outcome.moving_s = since
        if outcome.recovered or since > self.fault_timeout_s:
            self.say(self.fault_line(outcome))
            return True
        return False

    @staticmethod
    def fault_line(o: FaultOutcome) -> str:
        f = o.fault
        what = (f"stall {f.target} (SIGSTOP {f.stall_s:g} s, pid {o.pid})" if f.kind == "stall"
                else f"kill -9 {f.target} (pid {o.pid})")
        moving = {"learner": "a new weights version", "scheduler": "an episode counted"}.get(
            f.kind, f"{f.target}'s transitions accepted" if f.target.startswith("actor-") else "transitions accepted")
        back = ("" if f.kind == "stall" else
                f"answered again after {o.back_s:.1f} s, " if o.back_s is not None else "!! not answering, ")
        after = "after SIGCONT" if f.kind == "stall" else "after the kill"
        tail = f"{moving} {o.moving_s:.1f} s {after}" if o.moving_s is not None else f"!! no {moving} within the deadline"
        return f"[{o.at_s / 60:5.1f} min] fault {o.number}: {what}: {back}{tail}"

    def chaos(self) -> None:
        """Faults by the schedule, one at a time, supervision, samples and a line a minute."""
        queue = list(self.schedule)
        next_at = queue[0].gap_s if queue else float("inf")
        pending: FaultOutcome | None = None
        last_sample, next_line = -1e9, 60.0
        while True:
            now = self.elapsed()
            self.supervise()
            if now - last_sample >= 1.0:
                self.sample()
                last_sample = now
            if pending is not None and self.step_fault(pending):
                pending = None
                next_at = max(next_at, now + 2.0)  # the run has a moment between two faults
            if pending is None and queue and now >= next_at and now < self.window_s:
                pending = self.inject(queue.pop(0))
                next_at = now + (queue[0].gap_s if queue else float("inf"))
            if now >= next_line:
                self.progress()
                next_line += 60.0
            if now >= self.window_s and pending is None:
                return
            time.sleep(0.25)

    # -- the end ----------------------------------------------------------------------------------
    def resume_stalled(self) -> None:
        for pid in list(self.stopped):
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
            self.stopped.pop(pid)

    def settle(self, timeout_s: float = 120.0) -> bool:
        """Until every service runs and answers, every actor is live and holds at most one batch
        unacknowledged (what it took back after a fault has been resent)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.supervise()
            status = self.cluster.status() or {}
            unacked = [self.actor_unacknowledged(f"actor-{i}") for i in range(self.actors)]
            if (len(status.get("live_actors") or {}) == self.actors and self.replay_health() and self.learner_health()
                    and all(u is not None and u <= 1 for u in unacked)):
                return True
            time.sleep(0.5)
        return False

    def final_flush(self) -> list[str]:
        """Stop the actors gracefully and read their final reports; the problems."""
        problems = []
        names = [f"actor-{i}" for i in range(self.actors)]
        stop_began = time.time()
        self.cluster._stop_all(names, timeout=60)
        for name in names:
            inc = self.current(name)
            path = self.run_dir / "actors" / name / "actor-final.json"
            try:
                if path.stat().st_mtime < stop_began - 1:
                    raise OSError("written before the stop")
                final = json.loads(path.read_text())
                inc.generated = int(final["generated"])
                inc.unacknowledged = int(final.get("unacknowledged_transitions") or 0)
                inc.ended = "stopped"
            except (OSError, ValueError, KeyError, TypeError) as exc:
                problems.append(f"{name} did not report its final flush ({exc})")
                inc.ended = "exited"
                inc.generated = int(self.readings.get(name, 0))
        killed = [n for n, _, was_killed in self.cluster.stop_report if was_killed]
        if killed:
            problems.append(f"killed after not stopping within 60 s: {', '.join(killed)}")
        return problems

    def run(self) -> ChaosResult:
        cluster = self.cluster
        problems: list[str] = []
        try:
            self.say(f"starting a local run in {self.run_dir}: router, replay, learner, scheduler, {self.actors} "
                     f"actor(s); {len(self.schedule)} faults planned over {self.minutes:g} min")
            self.start()
            self.say(f"training; chaos for {self.minutes:g} min (faults every {self.schedule_mean():.0f} s on average)")
            self.chaos()
            self.resume_stalled()
            if not self.settle():
                problems.append("the run did not settle within 120 s after the chaos (services answering, actors "
                                "live, their batches acknowledged)")
            self.sample()
            problems += self.final_flush()
            time.sleep(2.0)
            self.sample()
            final_status = self.cluster.status() or self.last_status
            replay = self.replay_health() or {}
            mark_path = self.run_dir / "learner" / "version"
        finally:
            self.resume_stalled()
            cluster.stop()
        self.tally.read()
        return self.check(final_status, replay, mark_path, problems)

    def schedule_mean(self) -> float:
        return sum(f.gap_s for f in self.schedule) / len(self.schedule) if self.schedule else float("nan")

    def check(self, final_status: dict, replay: dict, mark_path: Path, problems: list[str]) -> ChaosResult:
        unattributed = attribute(self.incarnations, self.tally)
        accepted_end = self.tally.end or 0  # the replay's count is its log's index: read after it stopped
        seen = max([v for _, v in self.accepted if v is not None] + [int(replay.get("accepted") or 0)])
        from curlnav.replay.service import read_dropped

        # the replay's drops over the run: its file, written as it stopped, covers its last inserts too
        dropped = sum(read_dropped(self.run_dir / "replay")[1].values())
        acc = account(self.incarnations, accepted_end, seen, dropped,
                      max(self.dropped_seen, int(replay.get("dropped") or 0)))
        if unattributed:
            problems.append(f"{unattributed} transitions in the replay's log from no actor process of this run")
        if self.tally.gaps or self.tally.missed or self.tally.unreadable:
            problems.append(f"the replay's log: index gaps {self.tally.gaps[:3]}, segments gone before read "
                            f"{self.tally.missed[:3]}, unreadable records {self.tally.unreadable}")
        # versions
        back = went_back(self.versions)
        highest = max((v for _, v in self.versions if v is not None), default=None)
        try:
            mark = int((mark_path).read_text().strip() or 0)
        except (OSError, ValueError):
            mark = None
        versions_ok = not back and highest is not None and mark is not None and mark >= highest
        first = next((v for _, v in self.versions if v is not None), None)
        self.say(f"versions: v{first} -> v{highest} over {sum(v is not None for _, v in self.versions)} samples, "
                 f"went back {len(back)} times{f' (first: {back[0][1]} -> {back[0][2]} at {back[0][0]:.0f} s)' if back else ''}"
                 f", version mark {mark}")
        # curriculum
        try:
            saved = json.loads((self.run_dir / "scheduler" / "state.json").read_text())
        except (OSError, ValueError):
            saved = None
        curriculum = curriculum_problems(saved, final_status, self.statuses)
        state = (saved or {}).get("state") or {}
        self.say(f"curriculum: stage {final_status.get('stage')} (index {state.get('stage')}, sub-step "
                 f"{state.get('substep')}), epoch {state.get('epoch')}, advances kept {len(state.get('history') or [])}, "
                 f"episodes {state.get('episodes')}" + (f"; !! {'; '.join(curriculum)}" if curriculum else ""))
        # policy
        versions, policy, leftovers = artefact_problems(self.run_dir / "learner" / "artefacts")
        self.say(f"policy: artefacts {', '.join(f'v{v}' for v in versions) or 'none'}: files and sha256 "
                 + ("match their metadata" if not policy else f"!! {'; '.join(policy[:3])}")
                 + (f"; {len(leftovers)} leftover(s): {', '.join(leftovers[:3])}" if leftovers else ""))
        # faults
        counts: dict[str, int] = {}
        for o in self.outcomes:
            counts[o.fault.kind] = counts.get(o.fault.kind, 0) + 1
        unrecovered = [o for o in self.outcomes if not o.recovered]
        if unrecovered:
            problems.append(f"{len(unrecovered)} fault(s) without recovery: "
                            + "; ".join(f"{o.number} {o.fault.kind} {o.fault.target}" for o in unrecovered[:3]))
        if self.unplanned:
            self.say(f"exits the bench did not cause: {'; '.join(self.unplanned[:5])}")
        killed = [i for i in self.incarnations if i.ended in ("killed", "exited")]
        self.say(f"final flush: {sum(i.ended == 'stopped' for i in self.incarnations)}/{self.actors} actors reported; "
                 f"actor processes {len(self.incarnations)} ({len(killed)} killed or crashed, holding "
                 f"{sum(max(i.generated, i.accepted) - i.accepted for i in killed)} transitions unacknowledged)")
        checks = {"versions monotonic": versions_ok, "curriculum intact": not curriculum, "policy intact": not policy}
        if problems:
            checks["recovered"] = False
            for p in problems:
                self.say(f"!! {p}")
        line = summary_line(self.minutes, counts, acc, checks)
        self.say(line)
        return ChaosResult(line, acc, checks, self.outcomes, problems + curriculum + policy, self.incarnations,
                           self.versions)


def prepare_run_dir(run_dir: str | Path) -> Path:
    """A fresh run folder: a missing or empty one, or one this bench made before (cleared);
    ``ValueError`` (one line) for any other, so a training run is never cleared by mistake."""
    path = Path(run_dir)
    if path.exists() and not path.is_dir():
        raise ValueError(f"--run-dir {path}: a file, not a folder")
    if path.is_dir() and any(path.iterdir()):
        if not (path / MARKER).is_file():
            raise ValueError(f"--run-dir {path} holds something this bench did not make: choose another folder")
        shutil.rmtree(path)
    path.mkdir(parents=True, exist_ok=True)
    return path


def run_chaos_bench(minutes: float, actors: int = 2, every_s: float = 30.0, seed: int = 0,
                    run_dir: str | Path = "runs/bench-chaos", stage_steps: int | None = None,
                    stall_s: tuple[float, float] = STALL_S, overrides: tuple[str, ...] = (), say=None) -> ChaosResult:
    """Run ``minutes`` of chaos on a fresh local run in ``run_dir`` (see the module docstring),
    print the fault, minute and summary lines, return the figures. ``stage_steps``: environment
    steps per curriculum step (default: about three advances over the run); ``overrides``: more
    experiment config settings (``section.field=value``)."""
    from curlnav.config import resolve_config

    if not (minutes > 0 and every_s > 0 and actors >= 1 and seed >= 0) or minutes * 60 / every_s > 10_000:
        raise ValueError(f"bench chaos: --minutes and --every-s must be > 0 (at most 10,000 faults), --actors at "
                         f"least 1 and --seed >= 0, got --minutes {minutes:g}, --every-s {every_s:g}, --actors "
                         f"{actors}, --seed {seed}")
    path = prepare_run_dir(run_dir)
    (path / MARKER).write_text(json.dumps({"minutes": minutes, "actors": actors, "every_s": every_s, "seed": seed}))
    # the learner sets the pace (one update per transition inserted): about 50 transitions/s on 2 busy cores
    steps = stage_steps or max(300, int(minutes * 60 * 50 / 4))
    curriculum = path / "chaos-curriculum.yaml"
    curriculum.write_text(chaos_curriculum(steps))
    experiment = resolve_config(overrides=[
        "replay.min_size=300", "exploration.warmup_steps=300", "d4pg.batch_size=64",
        f"curriculum.file={curriculum.resolve()}", f"seed={seed}", *overrides])
    run = ChaosRun(path, experiment, actors, every_s, seed, minutes, stall_s,
                   say=say or (lambda line: print(line, flush=True)))
    return run.run()
