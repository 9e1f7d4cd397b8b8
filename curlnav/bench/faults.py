"""``curlnav bench faults``: kill -9 each stateful service of a training run, start it again, and
print what was lost and how long the run took to recover. The same measurement drives the
container fault injection (``scripts/compose_faults.py``, Docker SDK), through ``FaultTarget``.

Figures per kill:
- replay: transitions accepted before the kill (the last status heard, at most ~1 s old, so a
  lower bound), transitions restored from the log after it (stored in the table: what the replay
  could not store is not restored), lost = accepted - restored (> 0 is a loss, drops included),
  dropped (the replay's count of accepted transitions it could not store, over the run), seconds
  until it answers again, seconds until inserts flow again;
- learner: last weights version before, first version after (must be higher), seconds until a
  new version is published;
- scheduler: episodes counted before and after, seconds until it answers again.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass

HELP = "kill -9 replay, learner and scheduler of a local run: what was lost"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--actors", type=int, default=2)
    p.add_argument("--warm-s", type=float, default=60.0, help="s of training before the first kill")
    p.add_argument("--run-dir", default="runs/bench-faults")


def main(args: argparse.Namespace) -> int:
    rows = run_fault_bench(actors=args.actors, warm_s=args.warm_s, run_dir=args.run_dir)
    return 0 if all(r.get("lost", 0) == 0 and r.get("forward", True) and r.get("back_s") is not None
                    for r in rows) else 1


def poll(predicate: Callable[[], object], timeout: float, every: float = 0.2):
    """The first truthy value of ``predicate`` within ``timeout`` s, else None."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(every)
    return None


@dataclass
class FaultTarget:
    """How to kill and start one service, whatever runs it (local process, container)."""

    name: str
    kill: Callable[[], None]
    start: Callable[[], None]


def measure_kill(target: FaultTarget, status_url: str, timeout: float = 180.0) -> dict:
    """Kill ``target`` (SIGKILL), start it again, and measure through the scheduler's status."""
    from curlnav.run.launch import http_json_or_none

    status = lambda: http_json_or_none(status_url)  # noqa: E731
    before = poll(lambda: (s := status()) and (s.get("replay") or {}).get("accepted") is not None and s, 30) or {}
    replay_before = before.get("replay") or {}
    learner_before = (before.get("learner") or {}).get("version") or 0
    episodes_before = before.get("episodes") or 0
    target.kill()
    killed = time.monotonic()
    target.start()
    row = {"service": target.name}
    if target.name == "replay":
        fresh = poll(lambda: (s := status()) and (r := s.get("replay") or {}).get("restored") is not None
                     and r.get("uptime_s", 1e9) < time.monotonic() - killed + 2 and r, timeout)
        back = time.monotonic() - killed if fresh else None
        flowing = poll(lambda: (s := status()) and ((s.get("replay") or {}).get("accepted") or 0)
                       > ((fresh or {}).get("accepted") or 0) and s, timeout)
        accepted = int(replay_before.get("accepted") or 0)
        restored = int((fresh or {}).get("restored") or 0)
        row.update(accepted_before=accepted, restored=restored, lost=max(0, accepted - restored),
                   dropped=int((fresh or {}).get("dropped") or 0), back_s=back,
                   inserts_again_s=(time.monotonic() - killed) if flowing else None)
    elif target.name == "learner":
        first = poll(lambda: (s := status()) and ((s.get("learner") or {}).get("uptime_s", 1e9)
                                                  < time.monotonic() - killed + 2) and s["learner"], timeout) or {}
        back = time.monotonic() - killed if first else None
        newer = poll(lambda: (s := status()) and ((s.get("learner") or {}).get("version") or 0)
                     > (first.get("version") or 0) and s, timeout)
        row.update(version_before=learner_before, version_after=first.get("version"), back_s=back,
                   new_version_s=(time.monotonic() - killed) if newer else None,
                   forward=bool(first.get("version") and first["version"] > learner_before))
    else:
        after = poll(lambda: status(), timeout) or {}
        row.update(episodes_before=episodes_before, episodes_after=after.get("episodes"),
                   back_s=(time.monotonic() - killed) if after else None)
    return row


def print_rows(rows: list[dict]) -> None:
    for row in rows:
        fields = ", ".join(f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()
                           if k != "service")
        print(f"kill -9 {row['service']}: {fields}", flush=True)


def run_fault_bench(actors: int = 2, warm_s: float = 60.0, run_dir: str = "runs/bench-faults") -> list[dict]:
    """A local run on open-room; after ``warm_s`` of training, kill -9 replay, learner and
    scheduler in turn (each back before the next); prints and returns the figures."""
    import shutil
    from pathlib import Path

    from curlnav.config import resolve_config
    from curlnav.run.launch import LocalCluster

    shutil.rmtree(run_dir, ignore_errors=True)
    experiment = resolve_config(overrides=["replay.min_size=500", "exploration.warmup_steps=500"])
    cluster = LocalCluster(Path(run_dir), experiment, actors=actors, run="faults",
                           extra={"learner": ["--publish-every", "20"]})
    cluster.start()
    rows = []
    try:
        print(f"training {actors} actors on open-room for {warm_s:.0f} s before the first kill...", flush=True)
        poll(lambda: (s := cluster.status()) and (s["learner"]["version"] or 0) >= 2 and s, 300)
        time.sleep(warm_s)
        for name in ("replay", "learner", "scheduler"):
            def kill(name=name):
                cluster.kill_process(name)

            def start(name=name):
                cluster.restart(name)

            rows.append(measure_kill(FaultTarget(name, kill, start), cluster.status_url))
            print_rows(rows[-1:])
            time.sleep(10.0)
    finally:
        cluster.stop()
    return rows
