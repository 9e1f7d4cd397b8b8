"""``curlnav status``: the curriculum scheduler's ``/status`` of a distributed run, for a person.

The target is the scheduler's URL, or a run folder whose ``run.json`` (written by the launcher)
names it; by default the newest run folder under ``runs/`` that has one. A run folder whose run
has finished (its scheduler gone, ``summary.json`` closed) gets the run's outcome instead:
why it stopped, its counts and its last evaluation (serial runs too). A run started from a policy
(``init_from``) also shows where it started and that policy's held-out success before any update
beside the newest evaluation's (``start_lines``), running or finished.
"""

from __future__ import annotations

import json
from pathlib import Path
from urllib.parse import urlsplit

from curlnav.nav.roles import NETWORK, ControlSteps
from curlnav.run.pull import http_get, unreachable_reason
from curlnav.run.record import control_text


def newest_run(root: str | Path = "runs") -> Path:
    """The run folder under ``root`` whose ``run.json`` was written last."""
    files = sorted(Path(root).glob("*/run.json"), key=lambda p: p.stat().st_mtime) if Path(root).is_dir() else []
    if not files:
        raise ValueError(f"no run folder with a run.json under {root}/: give a run folder or the scheduler's URL "
                         "(distributed runs write one; serial runs have no scheduler)")
    return files[-1].parent


def status_url(target: str | None, root: str | Path = "runs") -> str:
    """The ``/status`` URL for ``target``: a URL (``/status`` added when it has no path), a run
    folder (its ``run.json``'s ``status_url``), or None (the newest run folder)."""
    if target is not None and target.startswith(("http://", "https://")):
        return target.rstrip("/") + "/status" if urlsplit(target).path in ("", "/") else target
    folder = newest_run(root) if target is None else Path(target)
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such run folder (give a run folder or the scheduler's URL, http://...)")
    run_json = folder / "run.json"
    if not run_json.is_file():
        raise ValueError(f"no run.json in {folder}: is it a distributed run folder (serial runs have no scheduler)?")
    try:
        info = json.loads(run_json.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{run_json}: cannot read it as JSON: {exc}") from None
    url = info.get("status_url") if isinstance(info, dict) else None
    if not isinstance(url, str) or not url:
        raise ValueError(f"{run_json}: no status_url (the scheduler's /status URL)")
    return url


def fetch_status(url: str, timeout: float = 5.0) -> dict:
    """The scheduler's status as a dict; ``ValueError`` (one line) when it cannot be had."""
    try:
        body = http_get(url, timeout=timeout)
    except OSError as exc:
        raise ValueError(f"cannot reach {url} ({unreachable_reason(exc)}): is the run still going?") from None
    try:
        status = json.loads(body)
    except (UnicodeDecodeError, json.JSONDecodeError):
        status = None
    if not isinstance(status, dict) or "stage" not in status:
        raise ValueError(f"{url}: not a curlnav scheduler status (expected the JSON of the scheduler's /status)")
    return status


def _percent(rate) -> str:
    return "-" if rate is None else f"{rate:.0%}"


def _count(value, noun: str) -> str:
    """``"12 updates"``, or ``"no updates recorded"`` for a count nobody reported."""
    return f"no {noun} recorded" if value is None else f"{value} {noun}"


def _world_name(world: str) -> str:
    """A world file's stem, a built-in world's name."""
    return Path(world).stem if world.endswith((".yaml", ".yml")) else world


def _table(header: tuple[str, ...], rows: list[tuple]) -> list[str]:
    cells = [tuple(str(c) for c in header)] + [tuple(str(c) for c in row) for row in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(header))]
    return ["  " + "  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in cells]


def format_status(s: dict) -> str:
    """The status as lines of text for a terminal."""
    pair = s.get("substep_pair")
    lines = [f"curriculum {s.get('curriculum')}: stage {s.get('stage_index')} {s.get('stage')}, sub-step {s.get('substep')}"
             + (f" (pair {pair})" if pair else " (the world's own pairs)") + f", epoch {s.get('epoch')}"]
    criterion = s.get("criterion")
    goal = ("never advances (last stage)" if not criterion else
            f"advances at {criterion['compare']} {criterion['success_rate']:.0%} over {criterion['window']} episodes")
    lines.append(f"episodes {s.get('episodes')}: window success {_percent(s.get('window_success_rate'))} over "
                 f"{s.get('window_size')} episodes, {goal}; last 100 episodes {_percent(s.get('success_last_100'))}")
    shares = s.get("control_steps_last_100") or {}
    if set(shares) - {NETWORK}:  # the network trains inside helpers (``helpers.stack``)
        lines.append(f"control steps, last 100 episodes: {control_text(shares)}")
    learner, replay = s.get("learner") or {}, s.get("replay") or {}
    rate = learner.get("updates_per_s")
    if learner.get("version") is None:  # the learner has not reported to the scheduler yet
        lines.append("learner: no policy yet (the learner has not reported)")
    else:
        lines.append(f"learner: version {learner['version']}, {_count(learner.get('updates'), 'updates')}, "
                     f"{'-' if rate is None else f'{rate:.1f}'} updates/s")
    inserts = replay.get("insert_rate")
    if replay.get("size") is None:
        lines.append("replay: not reported yet")
    else:
        lines.append(f"replay: {replay['size']} transitions, {'-' if inserts is None else f'{inserts:.0f}'} inserts/s")
    actors = s.get("live_actors") or {}
    count = s.get("live_actor_count", len(actors))
    lines.append(f"live actors: {count}" + (f" (the {len(actors)} that reported last below)" if count > len(actors) else ""))
    if actors:
        rows = []
        for name, actor in sorted(actors.items()):
            a = actor.get("assignment") or {}
            last = actor.get("last_report") or {}
            rows.append((name, _world_name(a.get("world", "-")) if a else "-", (a.get("pair") or "random") if a else "-",
                         actor.get("episodes", 0),
                         ("success" if last.get("success") else "failure") if last else "-",
                         f"v{last['weights_version']}" if "weights_version" in last else "-"))
        lines += _table(("actor", "world", "pair", "episodes", "last episode", "weights"), rows)
    rates = s.get("success_by_world_pair") or {}
    if rates:
        lines.append("success by world/pair:")
        rows = []
        for key, v in sorted(rates.items()):
            world, _, pair = key.rpartition("/")
            rows.append((_world_name(world), pair or "random", v.get("episodes"), _percent(v.get("success_rate"))))
        lines += _table(("world", "pair", "episodes", "success"), rows)
    advances = s.get("advances") or []
    lines.append(f"advances: {len(advances) or 'none yet'}")
    for a in advances:
        lines.append(f"  epoch {a.get('epoch')}: to stage {a.get('stage')} sub-step {a.get('substep')} "
                     f"after {a.get('episodes')} episodes ({a.get('reason')})")
    return "\n".join(lines)


def finished_summary(folder: Path) -> dict | None:
    """A run folder's ``summary.json`` when its last session has ended (None while running, or
    without one)."""
    try:
        summary = json.loads((folder / "summary.json").read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(summary, dict) or summary.get("stop_reason") in (None, "running"):
        return None
    return summary


def _result(e: dict) -> str:
    collisions = e.get("collisions_per_episode")
    return (f"success {_percent(e.get('success_rate'))}"
            + ("" if collisions is None else f", {collisions:.2f} base collisions/episode") + f" on {e.get('target')}")


def start_lines(fields: dict) -> list[str]:
    """``fields`` (``summary.json``, or ``curlnav.run.record.start_fields`` of a running run) of a
    run started from a policy, as lines: where from, its held-out result before any update, and the
    newest evaluation's (after); nothing for a run of fresh networks."""
    record = fields.get("init_from")
    if not isinstance(record, dict):
        return []
    before, after = fields.get("before"), fields.get("after")
    files = record.get("sha256") or {}
    if not isinstance(before, dict):
        then = "not evaluated yet"
    elif "error" in before:
        then = f"not evaluated ({before['error']})"
    else:
        then = _result(before)
    now = ("no evaluation yet" if not isinstance(after, dict) else
           f"{_result(after)} (evaluation {after.get('evaluation')}"
           + ("" if after.get("version") is None else f", policy v{after['version']}") + ")")
    return [f"started from {record.get('path')} ({record.get('kind')}; sha256 of its {len(files)} files in summary.json)",
            f"before any update: {then}; after: {now}"]


def format_outcome(folder: Path, summary: dict) -> str:
    """A finished run's outcome (``summary.json``) as lines of text for a terminal."""
    from curlnav.run.record import absolute, policy_lines

    folder = absolute(folder)
    sessions = summary.get("sessions") or [{}]
    last = sessions[-1]
    minutes = (summary.get("elapsed_s") or 0.0) / 60
    lines = [f"run {folder} has finished: stopped ({summary.get('stop_reason')}), exit code {summary.get('exit_code', '-')}, "
             f"{len(sessions)} session{'s' if len(sessions) != 1 else ''}, {minutes:.1f} min of training "
             f"({last.get('mode', 'distributed')})",
             f"counts: {_count(summary.get('env_steps'), 'env steps')}, {_count(summary.get('updates'), 'updates')}"
             + (f", {summary['episodes']} episodes" if summary.get("episodes") is not None else "")]
    evals = summary.get("evals") or []
    final = summary.get("final_eval") or (evals[-1] if evals else None)
    if final:
        collisions = final.get("collisions_per_episode")
        version = final.get("version", final.get("policy_version"))
        lines.append(f"last evaluation: success {_percent(final.get('success_rate'))}"
                     + ("" if collisions is None else f", {collisions:.2f} base collisions/episode")
                     + ("" if version is None else f" (policy v{version})")
                     + f"; {len(evals)} evaluation{'s' if len(evals) != 1 else ''} in eval.csv")
    lines += start_lines(summary)
    shares = (summary.get("last_status") or {}).get("control_steps_last_100") \
        or ControlSteps(last.get("control_steps") or {}).shares()
    if set(shares) - {NETWORK}:  # trained inside helpers: who drove at the end (distributed) or all along (serial)
        lines.append(f"control steps in training ({'last 100 episodes' if summary.get('last_status') else 'last session'}): "
                     f"{control_text(shares)}")
    reached = summary.get("first_eval_reaching_80")
    if reached:
        lines.append(f"first evaluation at >= 80%: {reached['wall_s'] / 60:.1f} min, {reached['env_steps']} env steps")
    lines.append(policy_lines(folder))
    from curlnav.run.launch import shell_command

    lines.append(f"continue it: {shell_command('curlnav', 'train', '--run-dir', folder, '--resume')} "
                 "(with a larger --minutes or --max-env-steps)")
    return "\n".join(lines)


def run_status(target: str | None, raw_json: bool = False) -> int:
    """Print the scheduler's status, or a finished run's outcome from its ``summary.json``."""
    folder = None
    if target is None or not target.startswith(("http://", "https://")):
        folder = newest_run() if target is None else Path(target)
    try:
        status = fetch_status(status_url(target))
    except ValueError:
        summary = finished_summary(folder) if folder is not None else None
        if summary is None:
            raise
        print(json.dumps(summary, indent=2) if raw_json else format_outcome(folder, summary))
        return 0
    if raw_json:
        print(json.dumps(status, indent=2))
        return 0
    from curlnav.run.record import start_fields

    print("\n".join([format_status(status), *start_lines(start_fields(folder) if folder is not None else {})]))
    return 0
