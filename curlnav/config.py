"""The experiment config: everything that changes results, in one typed, frozen, validated tree.

``ExperimentConfig`` holds the environment, D4PG (networks and optimisation), the replay (its
size, warm-up, rate limit and prioritisation), exploration (per actor), the curriculum, the
evaluation protocol and the budget. Presets are values of it (``ExperimentConfig.preset``).
``curlnav.builder.D4PGBuilder`` makes every component from it, for the serial trainer and for
every service alike, so the two modes cannot drift. Service configs (``*ServiceConfig``) hold
only where and how a service runs (run name, router, ports, data folder, threads), never what
it learns.

Loading: ``load_config(path)`` (YAML or JSON, unknown keys refused with their dotted path),
``apply_overrides(cfg, ["d4pg.batch_size=512"])`` and ``overrides_from_environment()``
(``CURLNAV_D4PG__BATCH_SIZE=512``: section and field joined by a double underscore). Every
value is validated when the config is built; errors are ``ConfigError`` with one line naming the
field. ``config_hash(cfg)`` identifies a config: all services of one run must agree on it.
Units: metres, seconds, radians, kilograms; counts are environment steps or transitions.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from curlnav.files import FileRefused, loads_yaml, read_yaml, shown
from curlnav.sim.config import ConfigError, EnvConfig

__all__ = ["ConfigError", "D4PGConfig", "ReplayConfig", "ExplorationConfig", "HelpersConfig", "MemoryConfig",
           "CurriculumConfig",
           "EvaluationConfig", "BudgetConfig", "ExperimentConfig", "PRESETS", "load_config", "apply_overrides",
           "overrides_from_environment", "config_hash", "config_to_dict", "config_from_dict", "config_differences"]


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)


def positive_numbers(obj: Any, prefix: str, names: list[str]) -> None:
    for name in names:
        value = getattr(obj, name)
        _require(not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value) and value > 0,
                 f"{prefix}.{name} must be a positive number, got {value!r}")


# Network size limits (issue 35): a config, checkpoint or weights message asking for more is
# refused before anything is allocated. The paper's networks (512, 512, 256, 256) fit well inside.
MAX_HIDDEN_WIDTH = 4096  # units of one hidden layer
MAX_HIDDEN_LAYERS = 8
MAX_ATOMS = 1001
MAX_CONV_FILTERS = 512
MAX_POOL = 256


@dataclass(frozen=True)
class D4PGConfig:
    """Networks and optimisation of distributional DDPG. Sizes are bounded: ``MAX_HIDDEN_WIDTH``
    units per layer, ``MAX_HIDDEN_LAYERS`` layers, ``MAX_ATOMS``, ``MAX_CONV_FILTERS``,
    ``MAX_POOL``; with an observation layout, ``curlnav.learner.networks.check_network_size``
    bounds the parameters of each network."""

    preset: str = "default"  # the preset these values came from (informative)
    # "pooled" min-pools each range frame (max-pools each label frame) over windows of `pool`
    # beams into an MLP; "conv" is the paper's trunk: two Conv1D (32 filters, kernel 3) over the
    # 8 stacked scan channels.
    encoder: str = "pooled"
    pool: int = 4  # beams per window of the pooled encoder (241 -> 61)
    conv_filters: int = 32  # filters per Conv1D layer of the conv encoder
    hidden: tuple[int, ...] = (256, 256)  # MLP widths (ELU) of the actor and critic heads
    atoms: int = 51  # atoms of the categorical return distribution
    v_min: float = -50.0  # lower end of its support (return units; the goal reward is +200)
    v_max: float = 250.0  # upper end
    n_step: int = 5  # steps per n-step return
    discount: float = 0.99  # per environment step (0.2 s)
    batch_size: int = 256  # transitions per update
    actor_lr: float = 1e-4  # Adam learning rate of the actor
    critic_lr: float = 1e-4  # Adam learning rate of the critic
    target_update_period: int = 100  # updates between hard copies to the target networks
    grad_clip_norm: float = 40.0  # global gradient norm, per network
    seed: int = 0  # network initialisation
    #: weight of the mean squared pre-tanh output in the actor's loss (0: none, the default, left
    #: out of the config hash while 0). Keeps the actor off tanh's flat ends, where the critic's
    #: gradient vanishes (an output pinned at a bound, e.g. linear speed 0, cannot follow the
    #: critic back); 0.01 lets actions reach about 97-99 % of their bounds
    actor_saturation_penalty: float = field(default=0.0, metadata={"hash": "omit-default"})
    #: updates (batches) that train the critic alone, the actor frozen, when the networks start
    #: from a policy artefact (``init_from``), which ships the actor only: a fresh critic's gradient
    #: would drag a trained actor anywhere. 1000 is about 40 s at the 25-30 updates/s of 2 CPU cores,
    #: ten target-network copies; 0: none. A start without a critic only (a checkpoint, fresh
    #: networks) never waits. Left out of the config hash while at its default
    critic_warmup_updates: int = field(default=1000, metadata={"hash": "omit-default"})
    #: fine-tuning (``init_from``): how strongly the actor is held near the policy it started from.
    #: With a weight ``a`` > 0 the actor's loss is ``-Q / mean|Q| + a * |pi(s) - pi_0(s)|^2`` (the Q
    #: term normalised by its batch's mean magnitude, as TD3+BC does, so ``a`` does not depend on the
    #: reward's scale; the squared distance summed over the action's fractions), ``pi_0`` the starting
    #: actor, frozen: a critic that has seen the trained actor's actions only cannot drag it into
    #: actions it knows nothing about. 0 (the default, left out of the config hash): none
    anchor_weight: float = field(default=0.0, metadata={"hash": "omit-default"})

    def __post_init__(self) -> None:
        p = "d4pg"
        _require(isinstance(self.critic_warmup_updates, int) and not isinstance(self.critic_warmup_updates, bool)
                 and 0 <= self.critic_warmup_updates <= 10_000_000,
                 f"{p}.critic_warmup_updates must be a whole number of updates in 0..10000000, got "
                 f"{shown(self.critic_warmup_updates)}")
        _require(isinstance(self.anchor_weight, (int, float)) and not isinstance(self.anchor_weight, bool)
                 and math.isfinite(self.anchor_weight) and 0 <= self.anchor_weight <= 1000,
                 f"{p}.anchor_weight must be a number in 0..1000 (0: none), got {shown(self.anchor_weight)}")
        _require(self.encoder in ("pooled", "conv"), f"{p}.encoder must be 'pooled' or 'conv', got {self.encoder!r}")
        _require(isinstance(self.atoms, int) and not isinstance(self.atoms, bool) and 2 <= self.atoms <= MAX_ATOMS,
                 f"{p}.atoms must be an integer 2-{MAX_ATOMS}, got {shown(self.atoms)}")
        _require(self.v_min < self.v_max, f"{p}.v_min ({self.v_min}) must be below {p}.v_max ({self.v_max})")
        _require(0 < self.discount <= 1, f"{p}.discount must be in (0, 1], got {self.discount!r}")
        _require(isinstance(self.actor_saturation_penalty, (int, float)) and not isinstance(self.actor_saturation_penalty, bool)
                 and math.isfinite(self.actor_saturation_penalty) and 0 <= self.actor_saturation_penalty <= 10,
                 f"{p}.actor_saturation_penalty must be a number in [0, 10], got {shown(self.actor_saturation_penalty)}")
        positive_numbers(self, p, ["pool", "conv_filters", "n_step", "batch_size", "actor_lr", "critic_lr",
                                    "target_update_period", "grad_clip_norm"])
        _require(isinstance(self.hidden, tuple) and 0 < len(self.hidden) <= MAX_HIDDEN_LAYERS
                 and all(isinstance(h, int) and not isinstance(h, bool) and 0 < h <= MAX_HIDDEN_WIDTH for h in self.hidden),
                 f"{p}.hidden must be 1-{MAX_HIDDEN_LAYERS} integer widths of 1-{MAX_HIDDEN_WIDTH}, got {shown(self.hidden)}")
        _require(isinstance(self.pool, int) and self.pool <= MAX_POOL,
                 f"{p}.pool must be an integer of at most {MAX_POOL}, got {shown(self.pool)}")
        _require(isinstance(self.conv_filters, int) and self.conv_filters <= MAX_CONV_FILTERS,
                 f"{p}.conv_filters must be an integer of at most {MAX_CONV_FILTERS}, got {shown(self.conv_filters)}")

    def to_dict(self) -> dict:
        return config_to_dict(self)

    @staticmethod
    def from_dict(data: dict) -> D4PGConfig:
        """From ``to_dict`` output. Keys that older curlnav versions kept here (replay and
        exploration settings, now in their own sections) are ignored, so old checkpoints and
        weights messages still load."""
        legacy = {"exploration_sigma", "replay_min_size", "replay_max_size", "samples_per_insert",
                  "samples_per_insert_tolerance", "prioritized"}
        return config_from_dict(D4PGConfig, {k: v for k, v in data.items() if k not in legacy}, "d4pg")


@dataclass(frozen=True)
class ReplayConfig:
    """The replay table and its rate limiter (Reverb's ``SampleToInsertRatio``)."""

    capacity: int = 200_000  # transitions kept (FIFO)
    min_size: int = 2000  # transitions inserted before the first sample (the learner's warm-up)
    samples_per_insert: float = 64.0  # transitions sampled per transition inserted, on average; 0: no rate limit
    tolerance: float = 0.1  # how far the ratio may drift: see ``error_buffer``
    insert_batch: int = 64  # most transitions one insert brings (an actor's batch: 24 steps plus its environments' n-step tails)
    prioritized: bool = False  # sample by priority (critic loss) instead of uniformly
    priority_exponent: float = 0.6  # alpha: sampling probability ~ priority ** alpha
    importance_exponent: float = 0.4  # beta: importance weights (N P(i)) ** -beta, max-normalised

    def __post_init__(self) -> None:
        positive_numbers(self, "replay", ["capacity", "min_size", "tolerance", "insert_batch",
                                           "priority_exponent", "importance_exponent"])
        _require(not isinstance(self.samples_per_insert, bool) and isinstance(self.samples_per_insert, (int, float))
                 and math.isfinite(self.samples_per_insert) and self.samples_per_insert >= 0,
                 f"replay.samples_per_insert must be a number >= 0, got {self.samples_per_insert!r}")
        _require(self.min_size <= self.capacity,
                 f"replay.min_size ({self.min_size}) must not exceed replay.capacity ({self.capacity})")

    def error_buffer(self, batch_size: int) -> float:
        """The rate limiter's slack (transitions x samples): ``tolerance * min_size *
        samples_per_insert``, but never less than one sampled batch plus one insert of
        ``insert_batch`` transitions (``batch_size + samples_per_insert * insert_batch``), so
        that inserts and samples can never both be blocked (the one formula, for every mode)."""
        return max(self.tolerance * self.min_size * self.samples_per_insert,
                   batch_size + self.samples_per_insert * self.insert_batch)


@dataclass(frozen=True)
class ExplorationConfig:
    """How actors explore. Actor ``i`` (the serial trainer is actor 0) adds Gaussian noise of
    ``sigma_ladder[i % len(sigma_ladder)]`` times each action's half-range, clipped to the
    bounds; several actors thus explore at several scales, as Ape-X and D4PG's actors do."""

    sigma_ladder: tuple[float, ...] = (0.3, 0.5, 0.2)  # noise scale per actor index
    warmup_steps: int = 2000  # uniformly random actions at the start of a run, shared by the actors

    def __post_init__(self) -> None:
        _require(len(self.sigma_ladder) > 0 and all(isinstance(s, (int, float)) and 0 <= s <= 10 and math.isfinite(s)
                                                    for s in self.sigma_ladder),
                 f"exploration.sigma_ladder must be numbers in [0, 10], got {self.sigma_ladder!r}")
        _require(isinstance(self.warmup_steps, int) and self.warmup_steps >= 0,
                 f"exploration.warmup_steps must be a non-negative integer, got {self.warmup_steps!r}")

    def sigma(self, actor_index: int) -> float:
        """The noise scale of actor ``actor_index``."""
        return float(self.sigma_ladder[actor_index % len(self.sigma_ladder)])

    def warmup_share(self, actor_count: int) -> int:
        """Random-action steps each of ``actor_count`` actors takes."""
        return -(-self.warmup_steps // max(actor_count, 1))


INFERENCE_BACKENDS = ("onnx", "torch")  # how an actor runs its policy network: ONNX Runtime or PyTorch


@dataclass(frozen=True)
class ActorConfig:
    """How each actor process runs. Each actor may choose its own (a host with more cores per
    actor, another value), so this section is not part of the services' agreement hash."""

    #: environments one actor process steps together, one batched policy call per step: 8, the
    #: best ratio to the bare environment on one core (`curlnav bench actor`)
    envs_per_process: int = 8
    inference: str = "onnx"  # the policy network on ONNX Runtime (onnx) or PyTorch (torch); `curlnav bench actor`
    #: PyBullet scenes one actor process keeps built across world switches, all its environments
    #: together (each environment keeps ``scenes_per_process // envs_per_process``, at least 1).
    #: A scene is 20-30 MB of memory on a NAMO or SLAM-like floor (measured, docs/lab/notebook.md):
    #: 32 keep an actor near 1-1.5 GB; unbounded (16 per environment) one grew to 9 GB.
    scenes_per_process: int = field(default=32, metadata={"hash": "omit-default"})

    def __post_init__(self) -> None:
        _require(isinstance(self.scenes_per_process, int) and not isinstance(self.scenes_per_process, bool)
                 and 1 <= self.scenes_per_process <= 1024,
                 f"actor.scenes_per_process must be a whole number in 1..1024, got {self.scenes_per_process!r}")
        _require(self.inference in INFERENCE_BACKENDS,
                 f"actor.inference must be one of {', '.join(INFERENCE_BACKENDS)}, got {self.inference!r}")
        _require(isinstance(self.envs_per_process, int) and not isinstance(self.envs_per_process, bool)
                 and 1 <= self.envs_per_process <= 64,
                 f"actor.envs_per_process must be a whole number in 1..64, got {self.envs_per_process!r}")


#: ``helpers.stack``'s value for the stack the run's ``init_from`` artefact ships
INHERITED_HELPERS = "inherit"


@dataclass(frozen=True)
class HelpersConfig:
    """The stack the network trains inside (issue 53): each actor runs its behaviour policy behind
    these helpers, built by ``curlnav.nav.build_stack`` as evaluation builds them. Each transition
    keeps the command that was executed (a helper's takeover is a demonstration, which D4PG learns
    from off-policy), and each step a helper chose costs ``intervention_cost`` of reward, so the
    network learns to need them less. The share of episodes run with the helpers fades from
    ``share_start`` to ``share_end`` over ``fade_steps`` of each actor's environment steps.

    ``stack``: "" (the network alone, the default), the helpers' suffixes as an agent argument
    spells them (``+rescue+shield``: recovery and safety roles with default settings), or
    ``inherit``: the recovery and safety entries, with their settings, of the stack the
    ``init_from`` artefact ships, or a path: a stack file (``curlnav stack show AGENT --out FILE``)
    or a policy artefact folder, whose recovery and safety entries, with their settings, train in
    the loop (a policy trained from scratch behind the helpers another one ships with). Only roles
    that choose commands train in the loop: a perception
    stage or a global planner rewrites what the network sees, while the replay keeps what the
    environment gave (refused in one line when the run starts: ``curlnav.nav.training``)."""

    stack: str = ""
    #: reward taken from each control step a helper chose (the paper's step rewards are 0.1-0.2,
    #: a base collision -10): 0 learns from the takeovers without paying for them. Keep
    #: ``intervention_cost / (1 - d4pg.discount)`` well inside the critic's support (``d4pg.v_min``)
    intervention_cost: float = 0.0
    #: reward taken from each control step the safety role (the shield) chose, in place of
    #: ``intervention_cost``; None: ``intervention_cost``. A shield's takeover stands for a contact the
    #: network would have driven into, which the shield hides from it (the episode goes on without
    #: the collision's -10): a cost near a collision's teaches the network what the shield saw
    safety_cost: float | None = field(default=None, metadata={"hash": "omit-default"})
    share_start: float = 1.0  # fraction of episodes with the helpers at an actor's first step ...
    share_end: float = 1.0  # ... and from ``fade_steps`` environment steps on (linear between)
    fade_steps: int = 0  # 0: ``share_start`` throughout

    def __post_init__(self) -> None:
        _require(isinstance(self.stack, str) and len(self.stack) <= 200 and "\0" not in self.stack,
                 f"helpers.stack must be '', +SUFFIX... or {INHERITED_HELPERS}, got {shown(self.stack)}")
        for name in ("intervention_cost", "safety_cost", "share_start", "share_end"):
            value = getattr(self, name)
            cost = name.endswith("_cost")
            _require((value is None and name == "safety_cost")
                     or (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                         and value >= 0 and (cost or value <= 1)),
                     f"helpers.{name} must be a number in {'[0, inf)' if cost else '[0, 1]'}"
                     f"{' or none' if name == 'safety_cost' else ''}, got {shown(value)}")
        _require(isinstance(self.fade_steps, int) and not isinstance(self.fade_steps, bool) and self.fade_steps >= 0,
                 f"helpers.fade_steps must be a whole number of environment steps >= 0, got {shown(self.fade_steps)}")
        _require(self.fade_steps > 0 or self.share_end == self.share_start,
                 f"helpers.share_end ({self.share_end:g}) differs from share_start ({self.share_start:g}) but "
                 f"helpers.fade_steps is 0: give the steps to fade over")

    def share(self, steps: int) -> float:
        """The fraction of episodes run with the helpers after ``steps`` environment steps."""
        if not self.fade_steps or steps >= self.fade_steps:
            return self.share_end if self.fade_steps else self.share_start
        return self.share_start + (self.share_end - self.share_start) * steps / self.fade_steps


@dataclass(frozen=True)
class MemoryConfig:
    """The network's memory (issue 53, ``curlnav.memory``): the returns of recent scans kept in
    the robot's odometry frame, read as a ring of ``beams`` sectors round the robot (the distance
    to the nearest remembered return in each, at most ``range_m``), which the network reads beside
    its frame stack. ``beams`` 0 (the default): no memory, the paper's observation. The policy's
    side computes the ring (the actors, evaluation, the robot's node), never the simulator."""

    beams: int = 0  # sectors of the ring over 360 deg (72: 5 deg each); 0: no memory
    range_m: float = 8.0  # m, the ring's reach (a sector with nothing nearer reads this)
    steps: int = 150  # control steps a return is remembered (30 s at 5 Hz)
    stride: int = 3  # keep every stride-th scan (fewer points to read back each step)

    def __post_init__(self) -> None:
        from curlnav.layout import MAX_MEMORY_BEAMS, MAX_MEMORY_RANGE, MAX_MEMORY_STEPS

        for name, low, high in (("beams", 0, MAX_MEMORY_BEAMS), ("steps", 1, MAX_MEMORY_STEPS),
                                ("stride", 1, MAX_MEMORY_STEPS)):
            value = getattr(self, name)
            _require(isinstance(value, int) and not isinstance(value, bool) and low <= value <= high,
                     f"memory.{name} must be a whole number {low}-{high}, got {shown(value)}")
        _require(isinstance(self.range_m, (int, float)) and not isinstance(self.range_m, bool)
                 and math.isfinite(self.range_m) and 0 < self.range_m <= MAX_MEMORY_RANGE,
                 f"memory.range_m must be a distance above 0 and at most {MAX_MEMORY_RANGE:g} m, got {shown(self.range_m)}")
        _require(self.stride <= self.steps, f"memory.stride ({self.stride}) must not exceed memory.steps ({self.steps})")
        if not self.beams:  # no memory: its other settings would change the config's hash and nothing else
            changed = [f.name for f in dataclasses.fields(self) if f.name != "beams" and getattr(self, f.name) != f.default]
            _require(not changed, f"memory.{changed[0] if changed else ''} is set but memory.beams is 0 (no memory): "
                                  f"set memory.beams (72: 5 deg sectors) or leave the memory's settings out")


@dataclass(frozen=True)
class CurriculumConfig:
    """What to train on: one world (with its pairs, or random pairs), or a curriculum file."""

    world: str = "open-room"  # built-in name, world YAML or FAMILY:SEED; also the actors' fallback
    file: str = ""  # curriculum YAML for the scheduler; empty: train on `world` only

    def __post_init__(self) -> None:
        _require(isinstance(self.world, str) and self.world != "", "curriculum.world must name a world")


@dataclass(frozen=True)
class EvaluationConfig:
    """The held-out evaluation protocol (``curlnav.evaluation.protocol``): greedy policy, collisions
    counted and the trial goes on, start/goal pairs never drawn in training."""

    every_s: float = 120.0  # s of training between evaluations
    episodes: int = 50  # held-out start/goal pairs per evaluation
    max_episode_steps: int = 300  # 60 s at 5 Hz, the authors' evaluation timeout
    stop_at_success: float | None = None  # stop training once an evaluation reaches this rate

    def __post_init__(self) -> None:
        positive_numbers(self, "evaluation", ["every_s", "episodes", "max_episode_steps"])
        _require(self.stop_at_success is None or 0 < self.stop_at_success <= 1,
                 f"evaluation.stop_at_success must be in (0, 1], got {self.stop_at_success!r}")


@dataclass(frozen=True)
class BudgetConfig:
    """When training stops: whichever comes first."""

    minutes: float = 15.0  # wall-clock minutes, evaluations included
    max_env_steps: int | None = None  # environment steps over all actors

    def __post_init__(self) -> None:
        positive_numbers(self, "budget", ["minutes"])
        _require(self.max_env_steps is None or (isinstance(self.max_env_steps, int) and self.max_env_steps > 0),
                 f"budget.max_env_steps must be a positive integer, got {self.max_env_steps!r}")


def _training_env() -> EnvConfig:
    return EnvConfig(max_episode_steps=200, end_on_base_collision=True)


@dataclass(frozen=True)
class ExperimentConfig:
    """One experiment. ``env`` is the *training* environment (episodes end at a base collision,
    40 s); evaluation uses the same environment with collisions counted and its own timeout."""

    env: EnvConfig = field(default_factory=_training_env)
    d4pg: D4PGConfig = field(default_factory=D4PGConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    actor: ActorConfig = field(default_factory=ActorConfig)
    #: the helpers the network trains inside (``HelpersConfig``); left out of the hash while none
    helpers: HelpersConfig = field(default_factory=HelpersConfig, metadata={"hash": "omit-default"})
    #: the network's memory (``MemoryConfig``); left out of the hash while it has none
    memory: MemoryConfig = field(default_factory=MemoryConfig, metadata={"hash": "omit-default"})
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    budget: BudgetConfig = field(default_factory=BudgetConfig)
    seed: int = 0  # environment draws, exploration noise and sampling (each actor adds its index)
    #: the name of the robot profile (``curlnav.sim.robots``: husky, jackal or a profile file's
    #: ``name``) that set ``env.robot`` and the LiDAR fields; left out of the hash while it is the default
    robot: str = field(default="husky", metadata={"hash": "omit-default"})
    #: where the networks start (fine-tuning): a policy artefact folder (its actor; the critic starts
    #: fresh and warms up first, ``d4pg.critic_warmup_updates``), a run folder or a training
    #: checkpoint ``.safetensors`` (actor, critic and optimiser moments); empty: fresh networks. Its
    #: robot, observation layout and network shape must be the run's (``curlnav.learner.init_from``).
    #: Read by the learner (and by the actors: no random warm-up from a trained policy); left out
    #: of the hash while empty
    init_from: str = field(default="", metadata={"hash": "omit-default"})

    def __post_init__(self) -> None:
        _require(isinstance(self.robot, str) and bool(self.robot), f"robot must be a profile name, got {self.robot!r}")
        _require(isinstance(self.init_from, str) and len(self.init_from) <= 4096 and "\0" not in self.init_from,
                 f"init_from must be a path (a policy artefact folder, a run folder or a checkpoint), got "
                 f"{shown(self.init_from)}")
        _require(self.helpers.stack != INHERITED_HELPERS or bool(self.init_from),
                 f"helpers.stack: {INHERITED_HELPERS} takes the stack of the init_from artefact; set init_from "
                 f"(--init-from) or name the helpers (+rescue+shield)")
        _require(self.env.robot.name == self.robot,
                 f"env.robot is the {self.env.robot.name}'s, but robot says {self.robot}: set the robot with "
                 f"robot: NAME or FILE (or --robot), not env.robot fields alone")
        _require(isinstance(self.seed, int) and not isinstance(self.seed, bool) and self.seed >= 0,
                 f"seed must be a non-negative integer, got {self.seed!r}")
        _require(self.d4pg.seed >= 0, f"d4pg.seed must be non-negative, got {self.d4pg.seed!r}")
        _require(self.d4pg.pool <= self.env.lidar_beams,
                 f"d4pg.pool ({self.d4pg.pool}) must not exceed env.lidar_beams ({self.env.lidar_beams})")
        _require(self.replay.min_size >= self.d4pg.batch_size,
                 f"replay.min_size ({self.replay.min_size}) must be at least d4pg.batch_size ({self.d4pg.batch_size})")
        tails = self.actor.envs_per_process * self.d4pg.n_step
        _require(tails < self.replay.insert_batch,
                 f"actor.envs_per_process x d4pg.n_step ({self.actor.envs_per_process} x {self.d4pg.n_step} = {tails}) "
                 f"must be below replay.insert_batch ({self.replay.insert_batch}): an actor's batch carries each "
                 f"environment's n-step tail; lower actor.envs_per_process or raise replay.insert_batch")

    @property
    def eval_env(self) -> EnvConfig:
        """The evaluation environment: collisions counted, the trial goes on."""
        return dataclasses.replace(self.env, end_on_base_collision=False,
                                   max_episode_steps=self.evaluation.max_episode_steps)

    @staticmethod
    def preset(name: str) -> ExperimentConfig:
        """A named preset (``PRESETS``)."""
        if name not in PRESETS:
            raise ConfigError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
        return PRESETS[name]()


def _default() -> ExperimentConfig:
    """Sized for a laptop CPU: a pooled encoder and 256-256 heads (0.41 M parameters)."""
    return ExperimentConfig()


def _paper() -> ExperimentConfig:
    """The authors' network and settings: Conv1D trunk, 512-512-256-256 ELU heads, batch 512,
    10k warm-up, exploration sigma 1.0 clipped, for every actor. (51 atoms on [-40, 130] as
    published; we keep the wider support since the goal reward is +200.)"""
    return ExperimentConfig(
        d4pg=D4PGConfig(preset="paper", encoder="conv", hidden=(512, 512, 256, 256), batch_size=512),
        replay=ReplayConfig(min_size=10_000),
        exploration=ExplorationConfig(sigma_ladder=(1.0,)))


PRESETS: dict[str, typing.Callable[[], ExperimentConfig]] = {"default": _default, "paper": _paper}


# -- dictionaries, files, overrides ---------------------------------------------------------------
def config_to_dict(cfg: Any, for_hash: bool = False) -> Any:
    """A plain dict (tuples as lists) of a config dataclass, recursively. A dataclass with a
    ``config_dict()`` method gives its own (``SensorNoiseConfig``: magnitudes left to the preset are
    None). ``for_hash``: fields marked ``metadata={"hash": "omit-default"}`` are left out while they
    hold their default, so that adding such a field keeps the hash of every existing config."""
    if dataclasses.is_dataclass(cfg):
        if hasattr(cfg, "config_dict"):
            return cfg.config_dict(for_hash)
        return {f.name: config_to_dict(getattr(cfg, f.name), for_hash) for f in dataclasses.fields(cfg)
                if not (for_hash and _omitted_from_hash(f, getattr(cfg, f.name)))}
    if isinstance(cfg, tuple):
        return [config_to_dict(v, for_hash) for v in cfg]
    return cfg


def _omitted_from_hash(f: dataclasses.Field, value: Any) -> bool:
    if f.metadata.get("hash") != "omit-default":
        return False
    default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
    return value == default


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(value: Any, tp: Any, path: str) -> Any:
    """``value`` as type ``tp`` (from YAML, JSON or a command-line string)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None or (isinstance(value, str) and value.lower() in ("none", "null", "")):
            if type(None) in args:
                return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(value, inner[0], path)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{path} must be a mapping, got {shown(value)}")
        return config_from_dict(tp, value, path)
    if origin is tuple:
        if isinstance(value, str):
            value = [v for v in value.replace("[", "").replace("]", "").split(",") if v.strip()]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path} must be a list, got {shown(value)}")
        return tuple(_coerce(v, args[0], f"{path}[{i}]") for i, v in enumerate(value))
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "yes", "1", "on", "false", "no", "0", "off"):
            return value.lower() in ("true", "yes", "1", "on")
        raise ConfigError(f"{path} must be true or false, got {shown(value)}")
    if tp is int:
        if isinstance(value, bool):
            raise ConfigError(f"{path} must be an integer, got {shown(value)}")
        try:
            number = float(value) if isinstance(value, str) else value
            if isinstance(number, float) and (not math.isfinite(number) or number != int(number)):
                raise ValueError
            return int(number)
        except (TypeError, ValueError):
            raise ConfigError(f"{path} must be an integer, got {shown(value)}") from None
    if tp is float:
        if isinstance(value, bool):
            raise ConfigError(f"{path} must be a number, got {shown(value)}")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{path} must be a number, got {shown(value)}") from None
    if tp is str:
        if not isinstance(value, (str, int, float)) or isinstance(value, bool):
            raise ConfigError(f"{path} must be a string, got {shown(value)}")
        return str(value)
    return value


def config_from_dict(cls: type, data: dict, path: str = "") -> Any:
    """Build config dataclass ``cls`` from a dict; missing fields keep their defaults, unknown
    keys and bad values raise ``ConfigError`` naming their dotted path."""
    if not isinstance(data, dict):
        raise ConfigError(f"{path or 'config'} must be a mapping, got {type(data).__name__}")
    types_ = _field_types(cls)
    unknown = set(data) - set(types_)
    if unknown:
        where = f"{path}." if path else ""
        raise ConfigError(f"unknown config key {where}{sorted(unknown)[0]}; known: {', '.join(sorted(types_))}")
    values = {name: _coerce(value, types_[name], f"{path}.{name}" if path else name) for name, value in data.items()}
    try:
        return cls(**values)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{path or cls.__name__}: {exc}") from None


def experiment_from_dict(data: dict, base: ExperimentConfig | None = None) -> ExperimentConfig:
    """An ``ExperimentConfig`` from a dict laid over ``base`` (default: the default preset).
    The dict may name a ``preset`` to start from instead."""
    data = dict(data)
    preset = data.pop("preset", None)
    if preset is not None:
        base = ExperimentConfig.preset(str(preset))
    base_dict = config_to_dict(base or ExperimentConfig())
    if "robot" in data:  # the profile first; the file's own env fields then win
        own_name = data.get("env", {}).get("robot", {}).get("name") if isinstance(data.get("env"), dict) else None
        _with_robot(base_dict, data.pop("robot"), saved_name=own_name)
    return config_from_dict(ExperimentConfig, _merge(base_dict, data))


def _with_robot(data: dict, spec: Any, saved_name: Any = None) -> None:
    """Set ``data`` (a config dict) to robot profile ``spec`` (a built-in name or a profile file):
    ``robot`` becomes the profile's name, the env's robot and LiDAR its values. A no-op when ``data``
    already holds that robot (settings made after it stay); a name that is neither built in nor a
    file is accepted only as the one ``saved_name`` gives (a saved config: its env is resolved)."""
    from curlnav.sim.robots import PROFILES, load_profile

    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError(f"robot must be {', '.join(PROFILES)} or a profile file (.yaml), got {shown(spec)}")
    spec = spec.strip()
    if spec == data.get("robot") and data["env"]["robot"].get("name") == spec:
        return  # already this robot
    if spec not in PROFILES and not spec.endswith((".yaml", ".yml", ".json")) and spec == saved_name:
        data["robot"] = spec  # a saved config of a profile file: its env fields hold the robot
        return
    profile = load_profile(spec)
    if profile.name == data.get("robot") and data["env"]["robot"].get("name") == profile.name:
        return
    env = profile.apply(config_from_dict(EnvConfig, data["env"], "env"))
    data["env"] = config_to_dict(env)
    data["robot"] = profile.name


def _merge(base: dict, top: dict) -> dict:
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def load_config(path: str | os.PathLike, base: ExperimentConfig | None = None) -> ExperimentConfig:
    """Read a YAML (or JSON) experiment file: any subset of the fields, optionally ``preset:``."""
    path = Path(path)
    try:
        data = read_yaml(path, what="config file") or {}
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the config file: {exc.strerror or exc}") from None
    except FileRefused as exc:
        raise ConfigError(str(exc)) from None
    try:
        return experiment_from_dict(data, base)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def apply_overrides(cfg: ExperimentConfig, overrides: list[str]) -> ExperimentConfig:
    """Apply ``section.field=value`` overrides (``--set``), in order."""
    data = config_to_dict(cfg)
    for item in overrides:
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"an override must look like section.field=value, got {item!r}")
        if key == "robot":
            _with_robot(data, raw.strip())
            continue
        node = data
        parts = key.split(".")
        for part in parts[:-1]:
            if not isinstance(node.get(part), dict):
                raise ConfigError(f"unknown config key {key}")
            node = node[part]
        if parts[-1] not in node or isinstance(node[parts[-1]], dict):
            raise ConfigError(f"unknown config key {key}")
        try:
            node[parts[-1]] = loads_yaml(raw, f"--set {key}") if raw.strip() else raw
        except FileRefused as exc:
            raise ConfigError(str(exc)) from None
    return config_from_dict(ExperimentConfig, data)


#: environment variables that set one field each (what containers have always used)
ENV_ALIASES = {"CURLNAV_WORLD": "curriculum.world", "CURLNAV_CURRICULUM": "curriculum.file", "CURLNAV_SEED": "seed",
               "CURLNAV_ROBOT": "robot", "CURLNAV_INIT_FROM": "init_from"}


def overrides_from_environment(environ: dict[str, str] | None = None) -> list[str]:
    """``CURLNAV_<SECTION>__<FIELD>[__<FIELD>]=value`` variables as overrides, sorted by name
    (``CURLNAV_D4PG__BATCH_SIZE=512`` -> ``d4pg.batch_size=512``), after the aliases of
    ``ENV_ALIASES`` (``CURLNAV_WORLD`` ...). Empty variables count as unset."""
    environ = os.environ if environ is None else environ
    out = [f"{path}={environ[name]}" for name, path in ENV_ALIASES.items() if environ.get(name, "").strip()]
    for name in sorted(environ):
        if name.startswith("CURLNAV_") and "__" in name and environ[name].strip():
            key = ".".join(part.lower() for part in name[len("CURLNAV_"):].split("__"))
            out.append(f"{key}={environ[name]}")
    return out


def config_hash(cfg: ExperimentConfig) -> str:
    """SHA-256 of the config's canonical JSON: equal for equal configs, whatever the source. Fields
    added with ``metadata={"hash": "omit-default"}`` (``env.sensor_noise``) count only when set."""
    text = json.dumps(config_to_dict(cfg, for_hash=True), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def service_config_hash(cfg: ExperimentConfig) -> str:
    """The hash the services of a run must agree on: every section they use (not ``budget``
    nor ``evaluation``, which only the launcher reads, nor ``actor``, each actor's own choice)."""
    data = {k: v for k, v in config_to_dict(cfg, for_hash=True).items() if k not in ("budget", "evaluation", "actor")}
    return hashlib.sha256(json.dumps(data, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def config_differences(a: dict, b: dict, prefix: str = "") -> list[str]:
    """Dotted paths where two config dicts differ, with both values."""
    out = []
    for key in sorted(set(a) | set(b)):
        path = f"{prefix}{key}"
        va, vb = a.get(key), b.get(key)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += config_differences(va, vb, path + ".")
        elif va != vb:
            out.append(f"{path} {va!r} vs {vb!r}")
    return out


def config_to_yaml(cfg: ExperimentConfig) -> str:
    return yaml.safe_dump(config_to_dict(cfg), sort_keys=False)


def resolve_config(config_path: str | None = None, preset: str | None = None, overrides: list[str] | None = None,
                   environ: dict[str, str] | None = None) -> ExperimentConfig:
    """Preset (default ``default``), then the file, then ``CURLNAV_*`` variables, then
    ``overrides``: the order in which a later source wins."""
    cfg = ExperimentConfig.preset(preset or "default")
    if config_path:
        cfg = load_config(config_path, cfg)
    env_overrides = overrides_from_environment(environ)
    if env_overrides:
        cfg = apply_overrides(cfg, env_overrides)
    if overrides:
        cfg = apply_overrides(cfg, overrides)
    return cfg
