"""Where a run's networks start (``ExperimentConfig.init_from``, ``curlnav train --init-from``).

The source is one of:

- a policy artefact folder (``metadata.json``, ``actor.onnx``, ``policy.safetensors``): its actor.
  An artefact ships the actor's weights only, so the critic starts fresh and learns alone first,
  the actor frozen (``d4pg.critic_warmup_updates`` updates: ``D4PGState.actor_frozen_until``);
- a run folder: its checkpoint (``checkpoints/latest.safetensors`` of a serial run,
  ``learner/latest.safetensors`` of a distributed one);
- a training checkpoint ``.safetensors``: actor, critic, targets and Adam moments, trained on under
  this run's training settings (``adopt_training_config``).

``find_starting_point`` reads what the source is without loading a tensor (its metadata, the sha256
of each of its files); ``check_starting_point`` refuses (``ValueError``, one line) a source of
another robot, observation layout or network shape; ``starting_state`` makes the learner's state
from it. The update count starts at 0 either way.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from curlnav.config import D4PGConfig, ExperimentConfig
from curlnav.files import shown
from curlnav.layout import ObservationLayout
from curlnav.policy import PolicyArtefact, sha256_of
from curlnav.sim.robots import check_observation, check_robot

from .d4pg import (
    NETWORK_FIELDS,
    D4PGState,
    adopt_training_config,
    anchored_copy,
    init_state,
    load_checkpoint,
    network_differences,
)

#: where a run folder keeps its checkpoint: a serial run's, then a distributed run's learner's
RUN_CHECKPOINTS = ("checkpoints/latest.safetensors", "learner/latest.safetensors")
#: the D4PG fields that shape the actor (the others of ``NETWORK_FIELDS`` shape the critic alone)
ACTOR_FIELDS = ("encoder", "pool", "conv_filters", "hidden")
EXPECTED = ("expected a policy artefact folder (metadata.json, policy.safetensors), a run folder (with "
            + " or ".join(RUN_CHECKPOINTS) + ") or a checkpoint .safetensors written by curlnav train")
#: what an artefact's sizes are checked against (check_robot's footprint tolerance covers the rest)
SCALES = (("max_linear_speed", "a top linear speed", "m/s"), ("max_angular_speed", "a top turn rate", "rad/s"),
          ("arm_reach", "an arm reach", "m"))


@dataclass(frozen=True)
class StartingPoint:
    """A source of initial networks, read but not loaded."""

    source: str  # as given (init_from)
    path: Path  # the artefact folder or the checkpoint file it names, absolute
    kind: str  # "artefact" or "checkpoint"
    #: artefact-like metadata for the checks: ``observation`` (``layout``, ``lidar_fov_rad``),
    #: ``robot`` (when recorded), ``training.d4pg`` (when recorded)
    metadata: dict = field(repr=False)
    sha256: dict[str, str] = field(default_factory=dict)  # file name -> digest, of every file of the source

    @property
    def has_critic(self) -> bool:
        return self.kind == "checkpoint"

    @property
    def stack(self) -> dict | None:
        """The navigation stack the source ships its policy with (an artefact's ``metadata.json``
        ``"stack"``; a checkpoint of a run that started from such an artefact records it too), or
        None: a fine-tuned policy is shipped behind the same helpers."""
        stack = self.metadata.get("stack")
        return stack if isinstance(stack, dict) else None

    @property
    def what(self) -> str:
        return f"init_from {self.source}"

    def record(self) -> dict:
        """What a run records of where it started (``summary.json``'s ``init_from``)."""
        return {"path": str(self.path), "kind": self.kind, "sha256": dict(self.sha256)}


def find_starting_point(source: str) -> StartingPoint:
    """The artefact, run folder or checkpoint ``source`` names, its files' digests checked against
    an artefact's ``metadata.json`` (``ValueError``, one line, when it is none of them)."""
    path = Path(source).absolute()
    if not source:
        raise ValueError(f"init_from is empty; {EXPECTED}")
    if not path.exists():
        raise ValueError(f"init_from {source}: no such file or folder; {EXPECTED}")
    if path.is_dir():
        if (path / "metadata.json").exists():
            return _artefact(source, path)
        for relative in RUN_CHECKPOINTS:
            if (path / relative).is_file():
                return _checkpoint(source, path / relative)
        raise ValueError(f"init_from {source}: a folder without metadata.json or a checkpoint; {EXPECTED}")
    return _checkpoint(source, path)


def _artefact(source: str, folder: Path) -> StartingPoint:
    what = f"init_from {source}"
    metadata = PolicyArtefact.read_metadata(folder)  # ArtefactError (a ValueError), one line
    listed = PolicyArtefact.listed_files(folder)
    if "policy.safetensors" not in listed:
        raise ValueError(f"{what}: its metadata.json lists no policy.safetensors (the actor's weights to start "
                         f"from); export the policy again with this curlnav")
    digests = {}
    for name, expected in sorted(listed.items()):
        path = folder / name
        if path.is_symlink() or not path.is_file():
            raise ValueError(f"{what}: missing {name}" + (" (a symlink)" if path.is_symlink() else ""))
        actual = sha256_of(path)
        if actual != expected:
            raise ValueError(f"{what}: {name} has sha256 {actual}, its metadata.json says {expected}; refused")
        digests[name] = actual
    digests["metadata.json"] = sha256_of(folder / "metadata.json")
    return StartingPoint(source, folder, "artefact", metadata, digests)


def _checkpoint(source: str, path: Path) -> StartingPoint:
    from safetensors import SafetensorError, safe_open

    what = f"init_from {source}"
    try:
        with safe_open(str(path), framework="pt") as f:
            header = f.metadata() or {}
    except (SafetensorError, OSError) as exc:
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"{what}: {path} is not a safetensors file ({shown(detail, 120)[1:-1]}); {EXPECTED}") from None
    try:
        meta = json.loads(header["curlnav"])
        if meta.get("format") != "curlnav-d4pg-checkpoint":
            raise ValueError
        config, layout = D4PGConfig.from_dict(meta["config"]), ObservationLayout(**meta["layout"])
    except (KeyError, TypeError, ValueError, AttributeError):
        raise ValueError(f"{what}: {path} is not a curlnav training checkpoint; {EXPECTED}") from None
    extra = meta.get("extra") if isinstance(meta.get("extra"), dict) else {}
    observation: dict = {"layout": layout.to_dict()}
    if isinstance(extra.get("lidar_fov_rad"), (int, float)):
        observation["lidar_fov_rad"] = float(extra["lidar_fov_rad"])
    metadata: dict = {"observation": observation, "training": {"d4pg": config.to_dict()}}
    if isinstance(extra.get("robot"), dict):
        metadata["robot"] = extra["robot"]
    if isinstance(extra.get("stack"), dict):
        metadata["stack"] = extra["stack"]
    return StartingPoint(source, path, "checkpoint", metadata, {path.name: sha256_of(path)})


def inherited_stack(init_from: str) -> dict | None:
    """The stack a run started from ``init_from`` ships its policies with (``StartingPoint.stack``):
    its artefacts' ``metadata.json`` and its checkpoints carry it. None without ``init_from``."""
    return find_starting_point(init_from).stack if init_from else None


def check_starting_point(point: StartingPoint, experiment: ExperimentConfig) -> None:
    """Refuse (``ValueError``, one line) a source that this run's networks cannot start from: a
    policy of another robot (``check_robot``) or of other action scales (an action means a fraction
    of the robot's top speeds and arm reach), another observation (``check_observation``: beams,
    field of view, range, frames) or other network settings (an artefact's actor: encoder, pool,
    filters, widths; a checkpoint's critic too: atoms and support). An artefact's weights are loaded
    into an actor of this run's shape, so a mismatch is found here and not in the learner."""
    env, robot, what = experiment.env, experiment.env.robot, point.what
    if point.kind == "artefact" or "robot" in point.metadata:  # an old checkpoint records no robot
        check_robot(point.metadata, robot, what)
        recorded = point.metadata.get("robot") or {}
        for key, label, unit in SCALES:
            value = recorded.get(key)
            if isinstance(value, (int, float)) and not isinstance(value, bool) and abs(value - getattr(robot, key)) > 1e-6:
                raise ValueError(f"{what}: trained for {label} of {value:g} {unit}, this run's {robot.name} has "
                                 f"{getattr(robot, key):g} {unit} (an action is a fraction of it); fine-tune at the "
                                 f"policy's: --set env.robot.{key}={value:g}")
    check_observation(point.metadata, env, what)
    layout = point.metadata["observation"]["layout"]
    mine = ObservationLayout.of(env, experiment.memory)
    if layout != mine.to_dict():
        raise ValueError(f"{what}: its observation layout {layout} is not this run's {mine.to_dict()}; refused")
    recorded_d4pg = (point.metadata.get("training") or {}).get("d4pg")
    fields = NETWORK_FIELDS if point.has_critic else ACTOR_FIELDS
    if isinstance(recorded_d4pg, dict):
        try:
            recorded_config = D4PGConfig.from_dict(recorded_d4pg)
        except ValueError:
            recorded_config = None  # an artefact of another curlnav: the weights themselves are checked below
        if recorded_config is not None:
            differences = [d for d in network_differences(recorded_config, experiment.d4pg)
                           if d.split()[0].split(".")[1] in fields]
            if differences:
                raise ValueError(f"{what}: its networks differ from this experiment's ({'; '.join(differences)}); "
                                 f"fine-tune with the same network settings and environment")
    if point.kind == "artefact":
        _artefact_actor(point, experiment.d4pg, mine)


def _artefact_actor(point: StartingPoint, config: D4PGConfig, layout: ObservationLayout, device=None):
    """An actor of this run's shape with the artefact's weights, the bytes read once and checked
    against the digest recorded (``ValueError``, one line, when they changed or do not fit)."""
    from safetensors import SafetensorError
    from safetensors.torch import load as load_tensors

    from .networks import Actor, check_network_size

    data = (point.path / "policy.safetensors").read_bytes()
    if hashlib.sha256(data).hexdigest() != point.sha256["policy.safetensors"]:
        raise ValueError(f"{point.what}: policy.safetensors changed since it was read; refused")
    check_network_size(layout, config)
    actor = Actor(layout, config)
    try:
        actor.load_state_dict(load_tensors(data))  # every name and shape
    except (SafetensorError, RuntimeError, KeyError) as exc:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        detail = lines[1] if len(lines) > 1 else lines[0] if lines else type(exc).__name__
        raise ValueError(f"{point.what}: its policy.safetensors does not fit this run's actor "
                         f"({shown(detail, 160)[1:-1]}); fine-tune with the network settings it was trained with") from None
    return actor if device is None else actor.to(device)


def starting_state(point: StartingPoint, experiment: ExperimentConfig, layout: ObservationLayout, device=None,
                   say: Callable[[str], None] = print) -> D4PGState:
    """The learner's state from ``point`` (checked: ``check_starting_point``), under this run's
    training settings, its update count 0. ``say`` is told, in one line each, where the networks
    came from and, for an artefact, that its critic starts fresh and warms up first."""
    config = experiment.d4pg
    if point.kind == "artefact":
        state = init_state(config, layout, device)
        actor = _artefact_actor(point, config, layout, state.device)
        state.actor.load_state_dict(actor.state_dict())
        state.target_actor.load_state_dict(actor.state_dict())
        state.actor_frozen_until = config.critic_warmup_updates
        if config.anchor_weight > 0:
            state.anchor = anchored_copy(state.actor)
        say(describe(point, config))
        return state
    state, _ = load_checkpoint(point.path, device)
    differences = network_differences(state.config, config)
    if state.layout != layout:
        differences.append("the observation layout")
    if differences:  # check_starting_point read the same header: only a file changed since gets here
        raise ValueError(f"{point.what}: its networks differ from this experiment's ({'; '.join(differences)}); "
                         f"fine-tune with the same network settings and environment")
    for change in adopt_training_config(state, config):
        say(f"fine-tuning with {change}")
    state.steps = 0
    state.actor_frozen_until = 0  # its critic came with it
    state.anchor = anchored_copy(state.actor) if config.anchor_weight > 0 else None  # this run's start, not the source's
    say(describe(point, config))
    return state


def describe(point: StartingPoint, config: D4PGConfig) -> str:
    """Where the networks come from, one line (with an artefact: that its critic starts fresh and
    how it warms up)."""
    anchor = (f"; the actor is held near where it started (d4pg.anchor_weight {config.anchor_weight:g})"
              if config.anchor_weight > 0 else "")
    if point.has_critic:
        return f"networks from {point.path} (fine-tuning: no random warm-up){anchor}"
    warmup = config.critic_warmup_updates
    return (f"networks from {point.path}: its actor (fine-tuning: no random warm-up); a policy artefact ships no "
            f"critic, so the critic starts fresh and "
            + (f"learns alone for the first {warmup} updates, the actor frozen (d4pg.critic_warmup_updates)"
               if warmup else "the actor learns from the first update (d4pg.critic_warmup_updates 0)") + anchor)


__all__ = ["ACTOR_FIELDS", "RUN_CHECKPOINTS", "StartingPoint", "check_starting_point", "describe",
           "find_starting_point", "inherited_stack", "starting_state"]
