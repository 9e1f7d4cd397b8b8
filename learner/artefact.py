"""Export a trained actor as a self-contained policy artefact.

A folder with:

- ``actor.onnx``: the actor, input ``observation`` float32 (B, obs_size), output ``action``
  float32 (B, 3) already inside the action bounds;
- ``policy.safetensors``: the actor's weights (for fine-tuning or other runtimes);
- ``metadata.json``: observation and action layout and scaling, robot, training steps,
  curriculum stage, source worlds, and the sha256 of each file above.

``curlnav.policy`` loads it with ONNX Runtime alone: no training code needed. ``load_policy`` reads
what an agent argument names (``curlnav eval``): an artefact folder or a training checkpoint.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

from curlnav.policy import sha256_of  # the one checksum of artefact files, for writer and reader
from curlnav.sim.config import EnvConfig
from curlnav.sim.robots import robot_metadata

if TYPE_CHECKING:
    from .d4pg import D4PGState

ARTEFACT_FORMAT = "curlnav-policy"
ARTEFACT_VERSION = 1




def training_worlds(curriculum_world: str, curriculum_file: str = "") -> tuple[list[str], dict]:
    """``(worlds, extra)`` for an artefact's ``training`` metadata: the curriculum's stage worlds
    (file stems, in stage order) and ``{"curriculum": name}`` when a curriculum file drives the
    run, else ``[curriculum_world]`` and nothing (``curriculum.world`` is only the actors'
    fallback under a curriculum)."""
    if not curriculum_file:
        return [curriculum_world], {}
    from curlnav.scheduler.curriculum import load_curriculum

    try:
        curriculum = load_curriculum(curriculum_file)
    except (ValueError, OSError):  # not readable here (a container without it): name it, never fail an export
        return [curriculum_world], {"curriculum": Path(curriculum_file).stem}
    worlds = [Path(w).stem if w.endswith((".yaml", ".yml")) else w for s in curriculum.stages for w in s.worlds]
    return list(dict.fromkeys(worlds)), {"curriculum": curriculum.name}


def export_policy(state: D4PGState, out_dir: str | Path, env_config: EnvConfig, *, worlds: list[str],
                  curriculum_stage: str = "none", env_steps: int = 0, version: int | None = None,
                  extra: dict | None = None, stack: dict | None = None) -> Path:
    """Write the artefact folder ``out_dir`` atomically (built beside it, then renamed). ``stack``:
    the navigation stack it ships with (``metadata.json``'s ``"stack"``: a fine-tuned policy keeps its
    source's, ``curlnav.learner.init_from.inherited_stack``); None: the network alone."""
    import torch  # here, so that reading a policy (``load_policy``) does not load torch
    from safetensors.torch import save_file

    from .networks import ACTION_HIGH, ACTION_LOW

    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=out_dir.name + ".", dir=out_dir.parent))
    actor = state.actor
    layout = state.layout
    was_training = actor.training
    actor.eval()
    cpu_actor = actor.to("cpu") if state.device.type != "cpu" else actor
    try:
        save_file({k: v.detach().cpu().contiguous() for k, v in cpu_actor.state_dict().items()},
                  str(tmp / "policy.safetensors"))
        example = torch.zeros(1, layout.size)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(cpu_actor, (example,), str(tmp / "actor.onnx"), input_names=["observation"],
                              output_names=["action"], dynamic_axes={"observation": {0: "batch"}, "action": {0: "batch"}},
                              dynamo=False)
    finally:
        if state.device.type != "cpu":
            actor.to(state.device)
        actor.train(was_training)
    robot = env_config.robot
    metadata = {
        "format": ARTEFACT_FORMAT,
        "version": ARTEFACT_VERSION,
        "policy_version": version if version is not None else state.steps,
        "created_unix_s": time.time(),
        "observation": {
            "size": layout.size,
            "layout": layout.to_dict(),
            "order": ["ranges (range_frames x beams, m, oldest first)", "labels (label_frames x beams, 1 = movable)",
                      *(["ring (memory_beams, m: the nearest remembered static return per sector over 360 deg, "
                         "sector 0 straight back, counter-clockwise; curlnav.memory)"] if layout.memory_beams else []),
                      "goal (goal_frames x [sign(dx)log(1+|dx|), sign(dy)log(1+|dy|), bearing rad], robot frame)"],
            "lidar_fov_rad": env_config.lidar_fov,
            "control_period_s": env_config.control_period,
        },
        "action": {
            "names": ["linear_velocity", "angular_velocity", "end_effector_displacement"],
            "low": list(ACTION_LOW), "high": list(ACTION_HIGH),
            "scale": [robot.max_linear_speed, robot.max_angular_speed, robot.arm_reach],
            "units": ["m/s", "rad/s", "m"],
            "note": "physical command = action * scale",
        },
        "robot": robot_metadata(env_config),
        "training": {"learner_steps": state.steps, "env_steps": env_steps, "curriculum_stage": curriculum_stage,
                     "worlds": list(worlds), "preset": state.config.preset, "d4pg": state.config.to_dict(),
                     **(extra or {})},
        "files": {name: sha256_of(tmp / name) for name in ("actor.onnx", "policy.safetensors")},
    }
    if stack:
        metadata["stack"] = stack
    (tmp / "metadata.json").write_text(json.dumps(metadata, indent=2))
    if out_dir.exists():
        shutil.rmtree(out_dir)
    tmp.rename(out_dir)
    return out_dir


POLICY_EXPECTED = "expected a policy artefact folder or a checkpoint .safetensors written by curlnav train"


def load_policy(path: str | Path):
    """A policy callable (``obs -> action``) from an artefact folder (or its ``metadata.json``) or a
    training checkpoint (.safetensors); ``ValueError`` naming the path when it is neither."""
    p = Path(path)
    if not p.exists():
        raise ValueError(f"no policy at {path}: {POLICY_EXPECTED}")
    if p.is_dir() or p.name == "metadata.json":
        from curlnav.policy import PolicyArtefact

        return PolicyArtefact(p if p.is_dir() else p.parent)
    return _checkpoint_policy(p)


def _checkpoint_policy(p: Path):
    """The actor of a D4PG checkpoint; ``ValueError`` naming the file when it is not one."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(p), framework="pt") as f:
            meta = f.metadata() or {}
    except SafetensorError as exc:
        raise ValueError(f"{p}: not a safetensors file ({exc}); {POLICY_EXPECTED}") from None
    if "curlnav" not in meta:
        raise ValueError(f"{p}: a safetensors file without curlnav checkpoint metadata; {POLICY_EXPECTED}")
    from .d4pg import load_checkpoint

    try:
        state, extra = load_checkpoint(p)
    except (SafetensorError, KeyError, TypeError, RuntimeError) as exc:
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"{p}: a damaged or incompatible curlnav checkpoint ({detail})") from None
    state.actor.eval()
    return CheckpointPolicy(state, extra)


class CheckpointPolicy:
    """The actor of a training checkpoint (``obs -> action``) with an artefact-like ``metadata``:
    its observation layout and, when the checkpoint records them, its robot and LiDAR field of view
    (``curlnav.sim.robots.sensor_metadata``), so that it is checked against the robot it is asked to
    drive as an artefact is."""

    def __init__(self, state, extra: dict) -> None:
        self.state = state
        observation: dict = {"layout": state.layout.to_dict()}
        if isinstance(extra.get("lidar_fov_rad"), (int, float)):
            observation["lidar_fov_rad"] = float(extra["lidar_fov_rad"])
        self.metadata: dict = {"observation": observation}
        if isinstance(extra.get("robot"), dict):
            self.metadata["robot"] = extra["robot"]

    def __call__(self, obs):
        from .d4pg import act

        return act(self.state.actor, obs)
