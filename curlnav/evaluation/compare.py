"""Compare agents on the same worlds, start/goal pairs and seeds: ``curlnav eval A B ...``.

An agent is a policy (``obs -> action``: an artefact folder or a checkpoint), alone or behind a
global plan (``curlnav.nav.global_planners.global_plan.GlobalPlanAgent``), or a planner of the registry
``curlnav.nav.PLANNERS`` (``curlnav.nav.make_agent`` makes either): the map-less
``tare-l`` and ``dwa`` (``curlnav.nav.controllers.local``) and the ``oracle`` with the true
map and pose (``curlnav.nav.global_planners.oracle.StaticMapPlanner``). Every
agent runs the evaluation protocol (``curlnav.evaluation.protocol.evaluate``: the evaluation environment,
collisions counted and the trial goes on, 60 s limit) on every world's pairs, once per seed
(a seed places the balls of worlds that re-place them on reset; the same for every agent).

Per agent and world (and over all worlds): success rate, base and arm (end-effector) collisions
per trial, time to goal and path length (over successful trials), and SPL, success weighted by
path length: ``mean(S_i * l_i / max(p_i, l_i))`` with ``p_i`` the path the base drove and
``l_i`` the shortest path on the static grid (``GridPlanner.shortest_length``: doors open,
movable objects ignored, the robot's half-width kept from walls) less the goal tolerance: a
trial succeeds, and stops, 0.8 m short of the goal, so that is the shortest successful path.

Outputs: ``comparison_table`` (agents side by side), ``write_csv`` (``episodes.csv``, a row per
episode; ``summary.csv``), ``draw_trajectories`` (a picture per world and pair with every agent's
path, as the paper's Fig. 7), and with ``Comparison.run(mcap=DIR, recorder=...)`` every episode as
a file in DIR made by the recorder the caller hands in (``curlnav eval --mcap`` hands in
``curlnav.ros2.recording.EpisodeMcap``: MCAP with ROS 2 schemas, as ``curlnav policy run --mcap``).
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from curlnav.evaluation.protocol import EVAL_SEED, StepRecorder, evaluate, held_out_pairs
from curlnav.nav.global_planners.oracle import GridPlanner, polyline_length
from curlnav.nav.roles import control_line
from curlnav.sim import EnvConfig, NamoEnv, StartGoal, World
from curlnav.worlds.core.pairs import draws_random_pairs
from curlnav.worlds.real import real_maps

DEFAULT_EPISODES = 50  # held-out pairs per world when neither pairs nor episodes are given
SEED_STRIDE = 100_000  # seed k's episodes place their balls from EVAL_SEED + k * SEED_STRIDE + i
OVERALL = "all"  # the world column of the summary over every world


def episode_pairs(world: World, names: Iterable[str] = (), pairs: int | None = None,
                  episodes: int | None = None) -> list[StartGoal]:
    """The pairs one seed runs on ``world``, one episode each: the pairs ``names`` (by name or
    index), repeated to ``episodes`` when given; else the first ``pairs`` held-out pairs; else
    ``episodes`` held-out pairs (default: each of a world's own held-out pairs once, else 50;
    ``held_out_pairs``: the world's held-out pairs or its own pairs in turn, or random draws for
    worlds that draw random pairs)."""
    names = list(names)
    if names and pairs is not None:
        raise ValueError("give start/goal pairs by name (--pair) or a number of them (--pairs), not both")
    if pairs is not None and episodes is not None:
        raise ValueError("--pairs runs each pair once per seed; --episodes goes with --pair or alone, not with --pairs")
    for label, n in (("pairs", pairs), ("episodes", episodes)):
        if n is not None and n < 1:
            raise ValueError(f"--{label} must be at least 1, got {n}")
    if names:
        chosen = [world.pair(int(n) if str(n).isascii() and str(n).isdigit() else n) for n in names]
        return [chosen[i % len(chosen)] for i in range(episodes or len(chosen))]
    if pairs is not None:
        return held_out_pairs(world, pairs) if draws_random_pairs(world) or world.held_out else list(world.pairs[:pairs])
    return held_out_pairs(world, episodes or len(world.held_out) or DEFAULT_EPISODES)  # its own held-out: each once


@dataclass(frozen=True)
class Episode:
    """One trial of one agent (a row of ``episodes.csv``); lengths in m, times in s."""

    agent: str
    world: str
    pair: str
    start_x: float
    start_y: float
    goal_x: float
    goal_y: float
    seed: int  # the episode's reset seed (ball places)
    success: bool
    time_s: float
    base_collisions: int  # steps with the base touching a wall
    arm_collisions: int  # steps with the end effector touching a wall
    path_length_m: float  # driven by the base
    shortest_path_m: float  # on the static grid, to within the goal tolerance
    spl: float  # success * shortest / max(driven, shortest)
    base_collision_events: int = 0  # contacts of the base with a wall, each counted once however long
    #: the trial's commands by the part of the stack that chose them (``ControlSteps.text``: ``network:812 rescue:40``)
    control_steps: str = ""
    trajectory: tuple[tuple[float, float], ...] = field(default=(), repr=False)  # not in the CSV

    def row(self) -> dict:
        out = {k: round(v, 4) if isinstance(v, float) else v for k, v in asdict(self).items()}
        del out["trajectory"]
        return out

    @staticmethod
    def columns() -> list[str]:
        """The columns of ``episodes.csv``, in order (``row``'s keys)."""
        return [f.name for f in fields(Episode) if f.name != "trajectory"]


@dataclass(frozen=True)
class Summary:
    """One agent on one world (or ``OVERALL``): a row of ``summary.csv``."""

    agent: str
    world: str
    episodes: int
    success_rate: float
    base_collisions_per_trial: float
    arm_collisions_per_trial: float
    time_to_goal_s: float  # mean over successful trials (nan if none)
    path_length_m: float  # mean over successful trials (nan if none)
    spl: float
    base_collision_events_per_trial: float = 0.0  # wall contacts of the base, each counted once
    #: the senses the trials ran with: ``exact``, or the sensor-noise preset and its overrides
    #: (``SensorNoiseConfig.describe``)
    senses: str = "exact"
    #: the share of control steps each part of the stack chose (``ControlSteps.line``)
    control_steps: str = ""

    def line(self) -> str:
        return (f"{self.agent} on {self.world}: success {self.success_rate:.0%} over {self.episodes} episodes, "
                f"{self.base_collisions_per_trial:.2f} base collisions/trial "
                f"({self.base_collision_events_per_trial:.2f} contact events), "
                f"{self.arm_collisions_per_trial:.2f} arm collisions/trial, "
                f"time to goal {_number(self.time_to_goal_s, '{:.1f} s')}, path {_number(self.path_length_m, '{:.1f} m')}, "
                f"SPL {self.spl:.2f}; senses {self.senses}" + (f"; {self.control_steps}" if self.control_steps else ""))


def _number(value: float, fmt: str) -> str:
    """``fmt`` of ``value``, or ``-`` for nan (a mean over no successful trial)."""
    return "-" if isinstance(value, float) and math.isnan(value) else fmt.format(value)


def spl_term(success: bool, shortest: float, driven: float) -> float:
    """``S * l / max(p, l)`` of one trial; a trial whose shortest path is unknown scores 0."""
    if not success or not math.isfinite(shortest) or shortest <= 0:
        return 0.0
    return shortest / max(driven, shortest)


class Comparison:
    """Runs ``agents`` (label -> policy or ``EpisodeAgent``) on ``worlds`` with ``pairs_of(world)``
    per seed: ``run(seeds, on_episode)`` -> episodes."""

    def __init__(self, agents: dict, worlds: list[World], pairs_of: Callable[[World], list[StartGoal]],
                 env_config: EnvConfig) -> None:
        names = [world.name for world in worlds]
        if len(set(names)) < len(names):
            raise ValueError(f"two worlds share a name: {', '.join(names)}")
        self.agents = agents
        self.worlds = worlds
        self.pairs = {world.name: pairs_of(world) for world in worlds}
        self.env_config = env_config
        self._planners: dict[str, GridPlanner] = {}
        self._shortest: dict[tuple, float] = {}

    def episode_count(self, seeds: int) -> int:
        return len(self.agents) * seeds * sum(len(p) for p in self.pairs.values())

    def shortest(self, world: World, pair: StartGoal) -> float:
        """Length (m) of the pair's shortest successful path: on the world's static grid, to
        within the goal tolerance (computed once per pair)."""
        key = (world.name, pair.x, pair.y, pair.gx, pair.gy)
        if key not in self._shortest:
            if world.name not in self._planners:
                self._planners[world.name] = GridPlanner(world, self.env_config.robot.base_width / 2)
            to_goal = self._planners[world.name].shortest_length((pair.x, pair.y), (pair.gx, pair.gy))
            self._shortest[key] = max(to_goal - self.env_config.goal_tolerance, 0.0)
        return self._shortest[key]

    def run(self, seeds: int = 1, on_episode: Callable[[Episode], None] | None = None,
            mcap: str | Path | None = None,
            recorder: Callable[[Path, NamoEnv, np.ndarray], StepRecorder] | None = None) -> list[Episode]:
        """Every agent on every world's pairs, ``seeds`` times; with ``mcap`` (a folder), each
        episode also written there as ``mcap_name(...)`` by ``recorder(path, env, observation)``
        (a ``StepRecorder`` per episode; ``curlnav eval`` hands in ``EpisodeMcap``: ROS 2 schemas)."""
        if mcap is not None and recorder is None:
            raise ValueError("Comparison.run(mcap=...) needs a recorder(path, env, observation)")
        episodes: list[Episode] = []
        names = mcap_agent_names(list(self.agents)) if mcap is not None else {}
        for world in self.worlds:
            for label, agent in self.agents.items():
                episodes += self.run_unit(world, label, agent, seeds, on_episode, mcap, recorder, names.get(label))
        return episodes

    def run_unit(self, world: World, label: str, agent, seeds: int = 1,
                 on_episode: Callable[[Episode], None] | None = None, mcap: str | Path | None = None,
                 recorder: Callable[[Path, NamoEnv, np.ndarray], StepRecorder] | None = None,
                 mcap_agent: str | None = None) -> list[Episode]:
        """One agent on one world's pairs, ``seeds`` times, in one environment of its own: a unit
        of ``run``, whose outcomes depend on nothing run before it (``curlnav.evaluation.parallel``
        runs units in worker processes). ``mcap_agent``: the agent's part of the MCAP file names
        (``mcap_agent_names`` of every label; default: the label made file-system safe)."""
        if mcap is not None and recorder is None:
            raise ValueError("Comparison.run(mcap=...) needs a recorder(path, env, observation)")
        episodes: list[Episode] = []
        pairs = self.pairs[world.name]
        # A fresh environment per agent: PyBullet's solver keeps warm-start impulses across
        # resets, so an agent run after another in the same environment would see physics
        # perturbed (by about 1e-10 m, growing) by the other's episodes, and two agents
        # with the same weights would score differently by their place in the list.
        env = NamoEnv(world, self.env_config)
        try:
            for k in range(seeds):
                base = EVAL_SEED + k * SEED_STRIDE

                def record(i: int, info: dict, base=base) -> None:
                    episodes.append(self._episode(label, world, pairs[i], base + i, info))
                    if on_episode:
                        on_episode(episodes[-1])

                steps = None if mcap is None else _mcap_recorder(recorder, Path(mcap), mcap_agent or _file_safe(label),
                                                                 world, pairs, k)
                evaluate(agent, world, pairs, self.env_config, seed=base, on_episode=record, env=env,
                         recorder=steps)
        finally:
            env.close()
        return episodes

    def _episode(self, agent: str, world: World, pair: StartGoal, seed: int, info: dict) -> Episode:
        """The record of a finished trial from its last step's ``info`` (with ``trajectory``)."""
        driven = polyline_length(info["trajectory"])
        shortest = self.shortest(world, pair)
        success = bool(info["is_success"])
        return Episode(agent, world.name, pair.name, pair.x, pair.y, pair.gx, pair.gy, seed, success,
                       info["steps"] * self.env_config.control_period, int(info["base_collisions"]),
                       int(info["end_effector_collisions"]), driven, shortest, spl_term(success, shortest, driven),
                       int(info.get("base_collision_events", 0)), info["control_steps"].text(),
                       tuple(map(tuple, info["trajectory"])))


@dataclass(frozen=True)
class ComparisonPlan:
    """What a comparison runs, made from plain data by one function (``curlnav eval``'s
    ``curlnav.evaluation.commands.eval_plan``, from the parsed options) in the command and again
    in every worker process (``curlnav.evaluation.parallel``): both build the worlds and the agents
    the same way, and a worker builds only the world and the agent of the unit it runs."""

    env_config: EnvConfig
    worlds: tuple  # world specs in order, plain data: a name, a YAML path, FAMILY:SEED, a BARN world's number
    world_of: Callable[[object], World]  # a world spec -> its World
    pairs_of: Callable[[World], list[StartGoal]]  # a world's pairs for one seed
    agents: tuple[str, ...]  # the AGENT arguments in order
    agent_of: Callable[[str], tuple[str, object]]  # an AGENT argument -> (label, policy or EpisodeAgent)
    seeds: int = 1  # runs of every pair (``Comparison.run``)
    senses: str = "exact"  # what the trials sense with (``SensorNoiseConfig.senses``)
    suite: Suite | None = None  # the suite that fixed the worlds and pairs, if one did
    mcap: str | None = None  # a folder for an MCAP file per episode (``Comparison.run``'s ``mcap``)
    recorder: Callable[[Path, NamoEnv, np.ndarray], StepRecorder] | None = None  # makes those files
    global_plan: bool = False  # every policy behind a plan on the true map (``--global-plan``)


def _file_safe(text: str) -> str:
    """``text`` with every run of characters other than letters, digits, ``.``, ``_``, ``-`` as one ``_``."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("._") or "_"


def mcap_agent_names(labels: list[str]) -> dict[str, str]:
    """The agents' part of their MCAP file names: a distinct file-system-safe name per agent
    label (``-2``, ``-3`` ... on a clash, in the labels' order)."""
    out: dict[str, str] = {}
    for label in labels:
        name, n = _file_safe(label), 1
        while (name if n == 1 else f"{name}-{n}") in out.values():
            n += 1
        out[label] = name if n == 1 else f"{name}-{n}"
    return out


def _mcap_recorder(make: Callable[[Path, NamoEnv, np.ndarray], StepRecorder], folder: Path, agent: str,
                   world: World, pairs: list[StartGoal], k: int) -> Callable:
    """``evaluate``'s ``recorder`` for seed ``k`` of ``agent`` on ``world``: ``make(path, env,
    observation)`` per episode, its file named by ``mcap_name``."""

    def recorder(i: int, env: NamoEnv, observation: np.ndarray) -> StepRecorder:
        return make(folder / mcap_name(agent, world.name, pairs[i].name, k * len(pairs) + i), env, observation)

    return recorder


def mcap_name(agent: str, world: str, pair: str, episode: int) -> str:
    """The MCAP file of one episode: ``AGENT__WORLD__PAIR__NNN.mcap``, each part file-system safe;
    ``episode`` counts the agent's episodes on the world (over seeds) from 0."""
    return f"{_file_safe(agent)}__{_file_safe(world)}__{_file_safe(pair)}__{episode:03d}.mcap"


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


def summarise(episodes: list[Episode], senses: str = "exact") -> list[Summary]:
    """Per agent: one summary per world (in order of first appearance), then ``OVERALL``; ``senses``:
    what the trials sensed with (``SensorNoiseConfig.describe``, ``exact`` for none)."""
    agents = list(dict.fromkeys(e.agent for e in episodes))
    worlds = list(dict.fromkeys(e.world for e in episodes))
    out = []
    for agent in agents:
        for world in [*worlds, OVERALL]:
            group = [e for e in episodes if e.agent == agent and (world == OVERALL or e.world == world)]
            if not group:
                continue
            won = [e for e in group if e.success]
            out.append(Summary(agent, world, len(group), len(won) / len(group),
                               _mean([e.base_collisions for e in group]), _mean([e.arm_collisions for e in group]),
                               _mean([e.time_s for e in won]), _mean([e.path_length_m for e in won]),
                               _mean([e.spl for e in group]), _mean([e.base_collision_events for e in group]),
                               senses, control_line(e.control_steps for e in group)))
    return out


METRICS = (  # (Summary field, row label, format)
    ("success_rate", "success", "{:.0%}"),
    ("base_collisions_per_trial", "base collisions/trial (steps)", "{:.2f}"),
    ("base_collision_events_per_trial", "base collision events/trial", "{:.2f}"),
    ("arm_collisions_per_trial", "arm collisions/trial", "{:.2f}"),
    ("time_to_goal_s", "time to goal (s)", "{:.1f}"),
    ("path_length_m", "path length (m)", "{:.1f}"),
    ("spl", "SPL", "{:.2f}"),
)


def comparison_table(summaries: list[Summary]) -> str:
    """Agents side by side (columns), a block of metric rows per world and one over all worlds."""
    agents = list(dict.fromkeys(s.agent for s in summaries))
    worlds = list(dict.fromkeys(s.world for s in summaries))
    by = {(s.agent, s.world): s for s in summaries}
    head = ["world", "metric", *agents]
    rows = []
    for world in worlds:
        if world == OVERALL and len(worlds) == 2:
            continue  # one world: its block already is the overall one
        count = max((by[(a, world)].episodes for a in agents if (a, world) in by), default=0)
        for n, (name, label, fmt) in enumerate(METRICS):
            cells = []
            for agent in agents:
                cells.append(_number(getattr(by[(agent, world)], name) if (agent, world) in by else float("nan"), fmt))
            rows.append([f"{world} ({count} episodes)" if n == 0 else "", label, *cells])
    widths = [max(len(str(r[i])) for r in [head, *rows]) for i in range(len(head))]
    lines = ["  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip() for r in [head, *rows]]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def write_csv(episodes: list[Episode], summaries: list[Summary], out: str | Path) -> dict[str, Path]:
    """``episodes.csv`` (a row per episode) and ``summary.csv`` in ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"episodes": out / "episodes.csv", "summary": out / "summary.csv"}
    columns = {"episodes": Episode.columns(),
               "summary": [f.name for f in fields(Summary)]}
    rows = {"episodes": [e.row() for e in episodes], "summary": [asdict(s) for s in summaries]}
    for key, path in paths.items():
        with open(path, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=columns[key])
            writer.writeheader()
            writer.writerows(rows[key])
    return paths


COLOURS = ("tab:green", "tab:purple", "tab:blue", "tab:brown", "tab:pink", "tab:cyan", "tab:olive")


def draw_trajectories(episodes: list[Episode], worlds: list[World], out: str | Path,
                      half_width: float) -> list[Path]:
    """A PNG per world and pair in ``out``: the static map, closed doors, the balls of worlds
    that keep them in place, the shortest path on the static grid (dashed) and each agent's
    trajectory of the first seed (a dot where it ended, a cross where it failed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from curlnav.sim.render import draw_world

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    agents = list(dict.fromkeys(e.agent for e in episodes))
    colour = {a: COLOURS[i % len(COLOURS)] for i, a in enumerate(agents)}
    written = []
    for world in worlds:
        shown = world.with_changes(balls=tuple(b for b in world.balls if b.region is None))
        planner = GridPlanner(world, half_width)
        first: dict[tuple[str, str], Episode] = {}
        for e in episodes:
            if e.world == world.name:
                first.setdefault((e.pair, e.agent), e)
        for pair_name in dict.fromkeys(p for p, _ in first):
            some = next(e for (p, _), e in first.items() if p == pair_name)
            pair = StartGoal(pair_name, some.start_x, some.start_y, 0.0, some.goal_x, some.goal_y)
            x0, y0, x1, y1 = world.bounds
            fig, ax = plt.subplots(figsize=(7, 7 * (y1 - y0) / max(x1 - x0, 1e-9) + 0.6), dpi=100)
            draw_world(ax, shown, pairs=[pair])
            shortest = planner.shortest_path((pair.x, pair.y), (pair.gx, pair.gy))
            if shortest is not None:
                ax.plot(shortest[:, 0], shortest[:, 1], "--", color="grey", lw=1, label="shortest (static map)")
            for agent in agents:
                e = first.get((pair_name, agent))
                if e is None:
                    continue
                traj = np.asarray(e.trajectory)
                outcome = "reached" if e.success else "failed"
                ax.plot(traj[:, 0], traj[:, 1], "-", color=colour[agent], lw=1.8,
                        label=f"{agent}: {outcome}, {e.time_s:.0f} s, {e.base_collisions} base coll.")
                ax.plot(traj[-1, 0], traj[-1, 1], "o" if e.success else "x", color=colour[agent], ms=7)
            ax.set_title(f"{world.name} / {pair_name}", fontsize=10)
            ax.legend(loc="upper left", bbox_to_anchor=(0.0, -0.1), fontsize=7, frameon=False)
            path = out / f"{world.name}-{pair_name}.png"
            fig.savefig(path, bbox_inches="tight")
            plt.close(fig)
            written.append(path)
    return written


# -- the unseen-world suite: Table II --------------------------------------------------------------------
@dataclass(frozen=True)
class Suite:
    """A fixed set of worlds nobody trains on, and which trials each world gets: ``trials``
    per world, as ``trials / ball_placements`` pairs with ``ball_placements`` placements each on
    worlds that re-place their balls on reset, else ``trials`` distinct pairs (a second placement
    of balls that never move would repeat the same trial and narrow the interval for nothing)."""

    name: str
    worlds: tuple[str, ...]  # FAMILY:SEED specs
    trials: int  # per world and agent
    ball_placements: int
    about: str

    def pairs_of(self, world: World) -> list[StartGoal]:
        """The world's trials in order (trial ``i`` places its balls from seed ``EVAL_SEED + i``)."""
        if any(ball.region is not None for ball in world.balls):
            pairs = episode_pairs(world, pairs=max(1, self.trials // self.ball_placements))
            return [p for _ in range(self.ball_placements) for p in pairs]
        return episode_pairs(world, pairs=self.trials)


#: ``curlnav eval AGENT... --suite unseen``: every family's seeds from 100 up are held out from
#: training (the shipped policies trained on barn-3x3 seed 0 and t-maze seed 0); 8 worlds x
#: 8 trials = 64 trials per agent, about a minute per agent on one core.
UNSEEN = Suite(
    "unseen",
    ("namo-office:300", "namo-office:301", "namo-indoor:300", "namo-indoor:301", "namo-auditorium:300",
     "namo-auditorium:301", "barn-3x3:300", "slam-office:300"),
    trials=8, ball_placements=2,
    about="NAMO office, indoor and auditorium at seeds 300 and 301 (8 of each world's own pairs, every one through "
          "a door; their balls stay put), barn-3x3 at seed 300 (4 held-out pairs x 2 placements of its 8 balls), "
          "slam-office at seed 300 (a 92 m x 72 m SLAM-like floor without balls, 8 held-out pairs 10-20 m apart)")
#: ``curlnav eval AGENT... --suite real``: nine real buildings as SLAM stacks mapped them, vendored
#: whole (``curlnav.worlds.real.real_maps.MAPS``: sources, licences, how unknown cells count); on each, 6 pairs
#: 6-20 m apart (shortest path at most 30 m, within the 60 s limit) and 8 balls on their shortest
#: paths, all from one seed: 54 trials per agent.
REAL = Suite(
    "real",
    real_maps.specs(),
    trials=real_maps.PAIRS, ball_placements=1,
    about=f"{len(real_maps.MAPS)} real buildings' SLAM maps, used whole (Willow Garage, Fraunhofer IPA's office, "
          "Yujin Robot's R&D office, six floors of two University of Tokyo buildings: a hall, offices, a lab, a corridor, a "
          "basement); 6 pairs 6-20 m apart and 8 balls on their shortest paths per map, fixed by seed; unknown cells "
          "are walls")
SUITES = {UNSEEN.name: UNSEEN, REAL.name: REAL}


def wilson_interval(successes: int, trials: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of a success rate (95 % for ``z = 1.96``): ``(low, high)``."""
    if trials <= 0:
        return (float("nan"), float("nan"))
    p = successes / trials
    centre = (p + z * z / (2 * trials)) / (1 + z * z / trials)
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / (1 + z * z / trials)
    return (max(0.0, centre - half), min(1.0, centre + half))


def table_ii(summaries: list[Summary]) -> str:
    """The paper's Table II layout as a Markdown table: a row per world (and one over all), a
    column per agent; each cell: success with its 95 % interval, base contact events per trial, arm
    contacts per trial (steps), time to goal (s, successful trials) and SPL; the caption names the senses."""
    agents = list(dict.fromkeys(s.agent for s in summaries))
    worlds = list(dict.fromkeys(s.world for s in summaries))
    by = {(s.agent, s.world): s for s in summaries}

    def cell(s: Summary | None) -> str:
        if s is None:
            return "-"
        low, high = wilson_interval(round(s.success_rate * s.episodes), s.episodes)
        return (f"{s.success_rate:.0%} ({low:.0%}-{high:.0%}) · {s.base_collision_events_per_trial:.2f} · "
                f"arm {s.arm_collisions_per_trial:.2f} · {_number(s.time_to_goal_s, '{:.0f} s')} · {s.spl:.2f}")

    lines = ["| world | " + " | ".join(agents) + " |", "|---|" + "---|" * len(agents)]
    for world in worlds:
        count = max((by[(a, world)].episodes for a in agents if (a, world) in by), default=0)
        name = f"**{world}**" if world == OVERALL else world
        lines.append(f"| {name} ({count}) | " + " | ".join(cell(by.get((a, world))) for a in agents) + " |")
    senses = ", ".join(dict.fromkeys(s.senses for s in summaries)) or "exact"
    lines += ["", "Each cell: success (95 % Wilson interval) · base contact events per trial · arm contacts per "
              "trial (steps) · time to goal (successful trials) · SPL. In brackets after the world: trials per "
              f"agent. Senses: {senses}."]
    return "\n".join(lines)
