"""The curriculum (Algorithm 1 of the paper) as a pure state machine, and its YAML file.

A curriculum is a list of stages. A stage has worlds and, optionally, ordered sub-steps (start/
goal pair names, the paper's p1..p4). Actors are assigned the current stage's worlds in turn
and, with sub-steps, the current sub-step's pair; without them the world draws its own pairs.
Episodes reported under the current assignment epoch fill a window; when the criterion holds
(e.g. success >= 70 % over the last 100 episodes, the paper's C1; > 50 % over the last 50 for
sub-steps, C2), the curriculum advances: next sub-step, else next stage. Every advance raises
the epoch, so reports from episodes that started before it do not count toward the new step.

```yaml
name: s1+s2
stages:
  - name: S1
    worlds: [barn-3x3-0.yaml]
    advance: {success_rate: 0.7, window: 100, compare: ">="}
  - name: S2
    worlds: [t-maze-0.yaml]
    substeps: [p1, p2, p3, p4]
    substep_advance: {success_rate: 0.5, window: 50, compare: ">"}
```

``worlds: {ranking: ranking.json, category: easy}`` takes the worlds, in order, from the file
written by ``curlnav worlds rank``.

A world entry may be a distribution of generated worlds instead of one world (issue 28):
``{family: barn-3x3, seeds: [0, 99], params: {fill_pct: [0.1, 0.3]}, every: 4}`` or
``t-maze-doors:0-99``. Actors draw a world of it per episode (``curlnav.worlds.distribution``);
the curriculum counts it as one task under its key. Seeds of 100 and above are held out
(``curlnav.worlds.core.heldout``): a stage or ``evaluate`` target that names one is refused at load.
``check_curriculum`` checks a distribution's first world (its sub-step pairs, if any).

Options beyond the paper (each one off unless the file sets it):

- ``replay_earlier: 0.2`` (per stage): that share of assignments goes back to a task of an
  earlier stage or sub-step (drawn uniformly among them), to keep what was learnt there.
  Replayed episodes are counted per world but never fill the current step's window.
- ``max_env_steps: 250000`` (in ``advance`` or ``substep_advance``): the step also ends after its
  episodes used that many environment steps, whichever comes first. The paper's C1 (70 % of the
  last 100 *training* episodes) may never hold: exploration noise, and episodes that end at the
  first collision, keep training success in barn under 70 % for 250k steps and more.
- ``evaluate: [{world: t-maze-0.yaml, pairs: [p1, p2, p3, p4]}]`` (top level): the fixed
  targets every held-out evaluation covers besides the current stage, so that conditions of an
  ablation are measured on the same tasks. Default: the last stage's worlds and sub-steps.
- ``sampler: learning-progress`` (per stage with two tasks or more: worlds x sub-steps; a stage
  without sub-steps has one task per world, e.g. per distribution): instead of one sub-step after
  the other (or the worlds in turn), every (world, sub-step pair) of the stage is a task and each
  assignment draws one by absolute learning progress (Portelas et al. 2020, Kanitscheider et al.
  2021): the gap between a fast (rate 0.1) and a slow (rate 0.02) moving average of the task's
  success, with a share of 0.2 drawn uniformly so that no task is starved. The stage's
  ``advance`` criterion then watches the last sub-step (the hardest pair) alone, or, without
  sub-steps, every world of the stage.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from curlnav.files import FileRefused, read_json, read_yaml, shown


class CurriculumError(ValueError):
    """The curriculum file is malformed; the message names the file and the field."""


@dataclass(frozen=True)
class Criterion:
    """``success_rate`` (``compare``: ">=" or ">") over the last ``window`` episodes; with
    ``source: evaluation``, over a held-out evaluation of the step's targets (greedy policy, at least
    ``window`` episodes in all) instead of the noisy training episodes. With ``max_env_steps``
    (an option beyond the paper), the step also ends once its episodes have used that many
    environment steps, whichever comes first: a stage that always ends."""

    success_rate: float
    window: int
    compare: str = ">="
    source: str = "training"  # or "evaluation"
    max_env_steps: int = 0  # environment steps of the step's episodes after which it ends anyway; 0: no limit

    def met_by(self, rate: float) -> bool:
        return rate >= self.success_rate if self.compare == ">=" else rate > self.success_rate

    def holds(self, outcomes: deque) -> bool:
        if len(outcomes) < self.window:
            return False
        rate = sum(outcomes) / len(outcomes)
        return rate >= self.success_rate if self.compare == ">=" else rate > self.success_rate


@dataclass(frozen=True)
class Stage:
    name: str
    worlds: tuple[str, ...]
    advance: Criterion | None = None  # None: the last stage, or a stage that never ends
    substeps: tuple[str, ...] = ()
    substep_advance: Criterion | None = None
    replay_earlier: float = 0.0  # share of assignments given to earlier stages' tasks
    sampler: str = "sequential"  # or "learning-progress" (see the module's docstring)


#: learning-progress sampler: moving-average rates of success (fast, slow), uniform share
LP_FAST, LP_SLOW, LP_EXPLORE = 0.1, 0.02, 0.2
SAMPLERS = ("sequential", "learning-progress")


@dataclass(frozen=True)
class Curriculum:
    name: str
    stages: tuple[Stage, ...]
    evaluate: tuple[tuple[str, str], ...] = ()  # fixed (world, pair or "") held-out targets

    def evaluation_targets(self) -> tuple[tuple[str, str], ...]:
        """``evaluate`` if given, else the last stage's worlds x sub-steps ("" = random pairs)."""
        if self.evaluate:
            return self.evaluate
        last = self.stages[-1]
        return tuple((w, p) for w in last.worlds for p in (last.substeps or ("",)))

    def to_dict(self) -> dict:
        def crit(c):
            return None if c is None else {"success_rate": c.success_rate, "window": c.window, "compare": c.compare,
                                           "source": c.source, "max_env_steps": c.max_env_steps}

        return {"name": self.name,  # criteria: see _criterion
                "stages": [{"name": s.name, "worlds": list(s.worlds), "advance": crit(s.advance),
                            "substeps": list(s.substeps), "substep_advance": crit(s.substep_advance),
                            "replay_earlier": s.replay_earlier, "sampler": s.sampler} for s in self.stages],
                "evaluate": [{"world": w, "pairs": [p] if p else []} for w, p in self.evaluate]}


def _criterion(path: Path, where: str, raw: Any) -> Criterion | None:
    if raw is None:
        return None
    if not isinstance(raw, dict) or set(raw) - {"success_rate", "window", "compare", "source", "max_env_steps"}:
        raise CurriculumError(f"{path}: {where} must be a mapping of success_rate, window, compare, source, "
                              f"max_env_steps")
    try:
        rate = float(raw["success_rate"])
        window = int(raw["window"])
    except (KeyError, TypeError, ValueError):
        raise CurriculumError(f"{path}: {where} needs a numeric success_rate and an integer window") from None
    compare = raw.get("compare", ">=")
    if not 0 <= rate <= 1 or window < 1 or compare not in (">=", ">"):
        raise CurriculumError(f"{path}: {where}: success_rate in [0, 1], window >= 1, compare '>=' or '>'")
    source = raw.get("source", "training")
    if source not in ("training", "evaluation"):
        raise CurriculumError(f"{path}: {where}.source must be 'training' or 'evaluation', got {shown(source)}")
    budget = raw.get("max_env_steps", 0)
    if isinstance(budget, bool) or not isinstance(budget, int) or budget < 0:
        raise CurriculumError(f"{path}: {where}.max_env_steps must be a whole number of environment steps >= 0 "
                              f"(0: no limit), got {shown(budget)}")
    return Criterion(rate, window, compare, source, budget)


def load_curriculum(path: str | Path) -> Curriculum:
    path = Path(path)
    try:
        raw = read_yaml(path, what="curriculum")
    except OSError as exc:
        raise CurriculumError(f"{path}: cannot read curriculum: {exc.strerror or exc}") from None
    except FileRefused as exc:
        raise CurriculumError(str(exc)) from None
    if not isinstance(raw, dict) or not isinstance(raw.get("stages"), list) or not raw["stages"]:
        raise CurriculumError(f"{path}: a curriculum is a mapping with a non-empty 'stages' list")
    unknown = set(raw) - {"name", "stages", "evaluate"}
    if unknown:
        raise CurriculumError(f"{path}: unknown keys {shown(sorted(map(str, unknown)))} (a curriculum has 'name', "
                              "'stages', 'evaluate')")
    stages = []
    for i, s in enumerate(raw["stages"]):
        where = f"stages[{i}]"
        if not isinstance(s, dict):
            raise CurriculumError(f"{path}: {where} must be a mapping")
        unknown = set(s) - {"name", "worlds", "advance", "substeps", "substep_advance", "replay_earlier", "sampler"}
        if unknown:
            raise CurriculumError(f"{path}: {where} has unknown keys {shown(sorted(map(str, unknown)))}")
        worlds = s.get("worlds")
        if isinstance(worlds, dict):
            worlds = _worlds_from_ranking(path, where, worlds)
        if not isinstance(worlds, list) or not worlds or not all(isinstance(w, (str, dict)) for w in worlds):
            raise CurriculumError(f"{path}: {where}.worlds must be a non-empty list of world names, files or "
                                  f"distributions ({{family, seeds: [lo, hi], params}})")
        worlds = [_stage_world(path, f"{where}.worlds[{j}]", w) for j, w in enumerate(worlds)]
        substeps = s.get("substeps") or []
        if not isinstance(substeps, list) or not all(isinstance(p, str) for p in substeps):
            raise CurriculumError(f"{path}: {where}.substeps must be a list of pair names")
        replay = s.get("replay_earlier", 0.0)
        if isinstance(replay, bool) or not isinstance(replay, (int, float)) or not 0 <= replay < 1:
            raise CurriculumError(f"{path}: {where}.replay_earlier must be a share in [0, 1), got {shown(replay)}")
        if replay and i == 0 and len(substeps) < 2:
            raise CurriculumError(f"{path}: {where}.replay_earlier: the first stage has nothing earlier to replay")
        sampler = s.get("sampler", "sequential")
        if sampler not in SAMPLERS:
            raise CurriculumError(f"{path}: {where}.sampler must be one of {', '.join(SAMPLERS)}, got {shown(sampler)}")
        if sampler == "learning-progress" and max(len(substeps), 1) * len(worlds) < 2:
            raise CurriculumError(f"{path}: {where}.sampler learning-progress needs at least two tasks "
                                  f"(worlds x substeps)")
        stages.append(Stage(str(s.get("name", f"S{i + 1}")), tuple(worlds),
                            _criterion(path, f"{where}.advance", s.get("advance")),
                            tuple(substeps), _criterion(path, f"{where}.substep_advance", s.get("substep_advance")),
                            float(replay), sampler))
    return Curriculum(str(raw.get("name", path.stem)), tuple(stages), _evaluate_targets(path, raw.get("evaluate")))


def _stage_world(path: Path, where: str, world: str | dict) -> str:
    """A stage's world entry as the name actors are assigned: a world file relative to the
    curriculum, a built-in name, ``FAMILY:SEED``, or a distribution's canonical key. Held-out
    seeds (``curlnav.worlds.core.heldout``) are refused: nobody trains or tunes on them."""
    from curlnav.worlds.core.heldout import is_held_out
    from curlnav.worlds.distribution import DistributionError, WorldDistribution, is_distribution

    try:
        if isinstance(world, dict):
            return WorldDistribution.from_spec(world).key
        if is_distribution(world):
            return WorldDistribution.parse(world).key
    except DistributionError as exc:
        raise CurriculumError(f"{path}: {where}: {exc}") from None
    if world.startswith("real:"):
        raise CurriculumError(f"{path}: {where}: {world[:60]} is a map of the real suite, kept for evaluation: "
                              f"nobody trains or tunes on it")
    family, sep, seed = world.rpartition(":")
    if sep and seed.isdigit() and is_held_out(family, int(seed)):
        raise CurriculumError(f"{path}: {where}: {world[:60]} is a held-out world (seeds >= 100 of every family are "
                              f"kept for unseen-world evaluation); use a seed below 100")
    return _world_path(path, world)


def _world_path(path: Path, world: str) -> str:
    """A world file named relative to the curriculum file; built-in names as they are."""
    return str(path.parent / world) if world.endswith((".yaml", ".yml")) and not Path(world).is_absolute() else world


def _evaluate_targets(path: Path, raw: Any) -> tuple[tuple[str, str], ...]:
    if raw is None:
        return ()
    if not isinstance(raw, list):
        raise CurriculumError(f"{path}: evaluate must be a list of {{world, pairs}} mappings")
    out = []
    for i, item in enumerate(raw):
        if (not isinstance(item, dict) or set(item) - {"world", "pairs"} or not isinstance(item.get("world"), str)
                or not isinstance(item.get("pairs", []), list) or not all(isinstance(p, str) for p in item.get("pairs", []))):
            raise CurriculumError(f"{path}: evaluate[{i}] must be {{world: NAME, pairs: [names]}} (pairs optional)")
        world = _stage_world(path, f"evaluate[{i}].world", item["world"])
        out.extend((world, p) for p in (item.get("pairs") or [""]))
    return tuple(out)


def check_curriculum(curriculum: Curriculum, source: str | Path = "") -> None:
    """Everything a run will need from ``curriculum``, checked before anything starts: every
    world of every stage loads, and every sub-step pair exists in each world of its stage.
    Raises ``CurriculumError`` (one line naming the file, stage and world) otherwise."""
    from curlnav.worlds.builtin import get_world
    from curlnav.worlds.core.world import WorldError

    where = f"{source or curriculum.name}"
    extra = [w for w, _ in curriculum.evaluate if all(w not in s.worlds for s in curriculum.stages)]
    stages = list(curriculum.stages) + ([Stage("evaluate", tuple(dict.fromkeys(extra)))] if extra else [])
    for stage in stages:
        for name in stage.worlds:
            try:
                world = get_world(name)
            except (WorldError, OSError, ValueError, KeyError) as exc:
                raise CurriculumError(f"{where}: stage {stage.name}: world {name!r} does not load: "
                                      f"{exc.args[0] if exc.args else exc}") from None
            pairs = {p.name for p in world.pairs}
            wanted = list(stage.substeps) + [p for w, p in curriculum.evaluate if w == name and p]
            missing = [p for p in dict.fromkeys(wanted) if p not in pairs]
            if missing:
                raise CurriculumError(f"{where}: stage {stage.name}: sub-step pair(s) {', '.join(missing)} do not exist "
                                      f"in world {world.name} (it has {', '.join(sorted(pairs)) or 'no named pairs'})")


def _worlds_from_ranking(path: Path, where: str, spec: dict) -> list[str]:
    ranking_path = path.parent / str(spec.get("ranking", ""))
    try:
        ranking = read_json(ranking_path, what="ranking")
    except (OSError, ValueError) as exc:
        raise CurriculumError(f"{path}: {where}.worlds: cannot read ranking {ranking_path}: {exc}") from None
    category = spec.get("category")
    names = ranking["order"] if category is None else ranking.get(category, [])
    files = spec.get("files", {})
    return [files.get(n, n) for n in names]


@dataclass
class CurriculumState:
    """Where the curriculum stands. ``record`` and ``assign`` are all a scheduler needs."""

    curriculum: Curriculum
    stage: int = 0
    substep: int = 0
    epoch: int = 0
    episodes: int = 0
    window: deque = field(default_factory=deque)
    per_world: dict = field(default_factory=dict)  # "world/pair" -> [episodes, successes]
    history: list = field(default_factory=list)  # advances: {epoch, stage, substep, episodes, reason}
    recent: deque = field(default_factory=lambda: deque(maxlen=100))  # last 100 outcomes, any epoch
    replays: int = 0  # assignments given to earlier tasks (``replay_earlier``)
    step_env_steps: int = 0  # environment steps of episodes reported under the current epoch
    progress: dict = field(default_factory=dict)  # "world/pair" -> [fast, slow, episodes] (learning progress)
    _next_world: int = 0
    rng: Any = None  # numpy Generator for ``replay_earlier`` and learning-progress draws (made on first use)
    seed: int = 0  # the experiment's seed: runs of different seeds draw differently

    @property
    def current(self) -> Stage:
        return self.curriculum.stages[self.stage]

    @property
    def learning_progress(self) -> bool:
        return self.current.sampler == "learning-progress"

    @property
    def criterion(self) -> Criterion | None:
        stage = self.current
        if self.learning_progress:
            return stage.advance
        if stage.substeps and self.substep < len(stage.substeps) - 1:
            return stage.substep_advance
        return stage.advance

    def _rng(self):
        if self.rng is None:
            import numpy as np

            self.rng = np.random.default_rng([self.seed, self.episodes])
        return self.rng

    def assign(self) -> tuple[str, str]:
        """The next (world, pair name or "") for an actor; worlds of the stage in turn, or, with
        the stage's ``replay_earlier`` share, a task of an earlier stage or sub-step; with the
        learning-progress sampler, the stage's task drawn by learning progress."""
        stage = self.current
        if stage.replay_earlier > 0:
            earlier = self.earlier_tasks()
            if earlier and self._rng().random() < stage.replay_earlier:
                self.replays += 1
                return earlier[int(self.rng.integers(len(earlier)))]
        if self.learning_progress:
            return self._draw_by_progress()
        world = stage.worlds[self._next_world % len(stage.worlds)]
        self._next_world += 1
        pair = stage.substeps[self.substep] if stage.substeps else ""
        return world, pair

    def stage_tasks(self) -> list[tuple[str, str]]:
        stage = self.current
        return [(w, p) for w in stage.worlds for p in (stage.substeps or ("",))]

    def task_progress(self) -> dict[str, float]:
        """Absolute learning progress per task of the stage (|fast - slow| success average)."""
        out = {}
        for world, pair in self.stage_tasks():
            fast, slow, _ = self.progress.get(f"{world}/{pair}", [0.0, 0.0, 0])
            out[f"{world}/{pair}"] = abs(fast - slow)
        return out

    def _draw_by_progress(self) -> tuple[str, str]:
        tasks = self.stage_tasks()
        rng = self._rng()
        lp = [self.task_progress()[f"{w}/{p}"] for w, p in tasks]
        total = sum(lp)
        if total <= 1e-9 or rng.random() < LP_EXPLORE:
            return tasks[int(rng.integers(len(tasks)))]
        return tasks[int(rng.choice(len(tasks), p=[x / total for x in lp]))]

    def earlier_tasks(self) -> list[tuple[str, str]]:
        """Every (world, pair) of the stages and sub-steps before the current one."""
        tasks = []
        for index, stage in enumerate(self.curriculum.stages[:self.stage + 1]):
            pairs = stage.substeps[:self.substep] if index == self.stage else stage.substeps
            if index == self.stage and not pairs:
                break
            tasks.extend((w, p) for w in stage.worlds for p in (pairs or ("",)))
        return tasks

    def is_current(self, world: str, pair: str) -> bool:
        """Whether an episode on (world, pair) is an episode of the current step (not a replay;
        with the learning-progress sampler: of the stage's last sub-step, which its criterion watches)."""
        stage = self.current
        if self.learning_progress:
            return world in stage.worlds and pair == (stage.substeps[-1] if stage.substeps else "")
        return world in stage.worlds and pair == (stage.substeps[self.substep] if stage.substeps else "")

    def record(self, world: str, pair: str, success: bool, epoch: int, steps: int = 0) -> bool:
        """Count one episode of ``steps`` environment steps; returns True if the curriculum
        advanced."""
        self.episodes += 1
        self.recent.append(bool(success))
        key = f"{world}/{pair}"
        stats = self.per_world.setdefault(key, [0, 0])
        stats[0] += 1
        stats[1] += int(success)
        if epoch == self.epoch and self.learning_progress and (world, pair) in self.stage_tasks():
            fast, slow, n = self.progress.get(key, [0.0, 0.0, 0])
            self.progress[key] = [fast + LP_FAST * (success - fast), slow + LP_SLOW * (success - slow), n + 1]
        crit = self.criterion
        if epoch == self.epoch:
            self.step_env_steps += max(int(steps), 0)
            if crit is not None and crit.max_env_steps and self.step_env_steps >= crit.max_env_steps:
                return self.advance(f"{self.step_env_steps} environment steps, the step's budget of "
                                    f"{crit.max_env_steps}")
        if epoch != self.epoch or not self.is_current(world, pair):
            return False  # started before the last advance, or a replay of an earlier task
        if crit is None or crit.source == "evaluation":
            return False
        self.window.append(bool(success))
        while len(self.window) > crit.window:
            self.window.popleft()
        if crit.holds(self.window):
            self.advance(f"success {sum(self.window) / len(self.window):.0%} over {len(self.window)} episodes")
            return True
        return False

    def record_evaluation(self, success_rate: float, episodes: int, epoch: int) -> bool:
        """A held-out evaluation of the current step's targets (``episodes`` in all, success
        ``success_rate``) of a policy evaluated at ``epoch``; advances when the step's criterion
        is ``source: evaluation`` and holds. Returns True if the curriculum advanced."""
        crit = self.criterion
        if crit is None or crit.source != "evaluation" or epoch != self.epoch or episodes < crit.window:
            return False
        if crit.met_by(success_rate):
            return self.advance(f"held-out success {success_rate:.0%} over {episodes} episodes")
        return False

    def advance(self, reason: str = "forced") -> bool:
        """Next sub-step, else next stage; False (and nothing changes) at the very end."""
        stage = self.current
        if stage.substeps and self.substep < len(stage.substeps) - 1 and not self.learning_progress:
            self.substep += 1
        elif self.stage < len(self.curriculum.stages) - 1:
            self.stage += 1
            self.substep = 0
        else:
            return False
        self.epoch += 1
        self.window.clear()
        self.step_env_steps = 0
        self.history.append({"epoch": self.epoch, "stage": self.current.name, "substep": self.substep,
                             "episodes": self.episodes, "reason": reason})
        return True

    def success_rate(self) -> float | None:
        return sum(self.window) / len(self.window) if self.window else None

    def to_dict(self) -> dict:
        return {"stage": self.stage, "substep": self.substep, "epoch": self.epoch, "episodes": self.episodes,
                "window": [int(x) for x in self.window], "per_world": self.per_world, "history": self.history,
                "next_world": self._next_world, "recent": [int(x) for x in self.recent], "replays": self.replays,
                "progress": self.progress, "step_env_steps": self.step_env_steps}

    @staticmethod
    def from_dict(curriculum: Curriculum, d: dict, seed: int = 0) -> CurriculumState:
        state = CurriculumState(curriculum, seed=seed)
        stage = int(d.get("stage", 0))
        if not 0 <= stage < len(curriculum.stages):
            raise CurriculumError(f"saved stage {stage} does not exist in curriculum {curriculum.name!r}")
        state.stage, state.substep, state.epoch = stage, int(d.get("substep", 0)), int(d.get("epoch", 0))
        state.episodes = int(d.get("episodes", 0))
        state.window = deque(bool(x) for x in d.get("window", []))
        state.per_world = {k: list(v) for k, v in d.get("per_world", {}).items()}
        state.history = list(d.get("history", []))
        state._next_world = int(d.get("next_world", 0))
        state.recent.extend(bool(x) for x in d.get("recent", []))
        state.replays = int(d.get("replays", 0))
        state.step_env_steps = int(d.get("step_env_steps", 0))
        state.progress = {k: [float(v[0]), float(v[1]), int(v[2])] for k, v in d.get("progress", {}).items()}
        return state
