"""One episode drawn: ``drive_and_draw`` (``curlnav policy run``, ``curlnav rollout``) drives an agent
for one episode through the evaluation protocol's loop and draws it to a PNG; ``EpisodeRecorder``
animates it as a GIF: the robot, its LiDAR hits and the movable objects, step by step, over the
world drawing of ``curlnav.sim.render`` (``curlnav policy run --gif``)."""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from curlnav.evaluation.protocol import StepRecorder, evaluate


def drive_and_draw(agent, world, pair, seed: int, cfg, out: str | os.PathLike, label: str, gif: bool = False,
                   mcap: str | os.PathLike | None = None,
                   recorder: Callable[[Path, object, np.ndarray], StepRecorder] | None = None) -> int:
    """One episode of ``agent`` (a policy, observation -> action, or an ``EpisodeAgent``) in
    ``world`` (a spec or a ``World``) from ``pair`` (``None``: drawn with ``seed``), run by
    ``curlnav.evaluation.protocol.evaluate`` in an environment of ``cfg`` and drawn to a PNG in
    ``out`` (with ``gif``, also animated step by step in a GIF beside it; with ``mcap``, also
    written to that file by ``recorder(path, env, observation)``, e.g.
    ``curlnav.ros2.recording.EpisodeMcap``). Prints a summary and the files; returns 0."""
    from curlnav.sim import NamoEnv
    from curlnav.sim.render import save_env_picture

    if mcap is not None and recorder is None:
        raise ValueError("drive_and_draw(mcap=...) needs a recorder(path, env, observation)")
    env = NamoEnv(world, cfg)
    frames = EpisodeRecorder(env) if gif else None
    written: list = []
    ended: list[dict] = []

    def steps(i: int, env: NamoEnv, observation: np.ndarray) -> StepRecorder:
        parts = [] if frames is None else [frames.start()]
        if mcap is not None:
            written.append(recorder(Path(mcap), env, observation))
            parts.append(written[-1])
        return _Both(parts)

    try:
        evaluate(agent, env.world, [pair], cfg, seed=seed, on_episode=lambda i, info: ended.append(info), env=env,
                 recorder=steps)
        info = ended[-1]
        folder = Path(out)
        folder.mkdir(parents=True, exist_ok=True)
        picture = folder / f"{label}-{env.world.name}-{info['pair']}.png"
        outcome = "reached the goal" if info["is_success"] else ("timed out" if info["truncated"] else "stopped")
        summary = (f"{label} on {env.world.name}/{info['pair']}: {outcome} after {info['steps']} steps "
                   f"({info['steps'] * cfg.control_period:.1f} s simulated), return {info['episode_return']:.1f}, "
                   f"base collisions {info['base_collisions']}, end-effector collisions "
                   f"{info['end_effector_collisions']}")
        save_env_picture(env, picture, title=summary.replace(" after", "\nafter", 1))
        print(summary)
        print(f"picture: {picture}")
        if frames is not None:
            animation = frames.save_gif(picture.with_suffix(".gif"),
                                        title=f"{label} on {env.world.name}/{info['pair']}")
            print(f"animation: {animation}")
        for file in written:
            print(f"mcap: {file.path}")
    finally:
        env.close()
    return 0


class _Both:
    """Several ``StepRecorder``s as one."""

    def __init__(self, parts: list) -> None:
        self.parts = parts

    def step(self, action: np.ndarray, observation: np.ndarray) -> None:
        for part in self.parts:
            part.step(action, observation)

    def close(self) -> None:
        for part in self.parts:
            part.close()


@dataclass(frozen=True)
class EpisodeFrame:
    """The state drawn for one step: robot pose (x, y, yaw, arm), movable objects, LiDAR."""

    step: int
    pose: tuple[float, float, float, float]
    balls: tuple[tuple[float, float], ...]
    doors: tuple[float, ...]
    boxes: tuple[tuple[float, float, float], ...]
    hits: np.ndarray | None
    labels: np.ndarray | None


class EpisodeRecorder:
    """``record()`` after ``reset`` and after every ``step`` of ``env``; ``save_gif(path)``. As the
    protocol's ``StepRecorder``: ``start()`` after ``reset`` (records and returns itself), then
    ``step(action, observation)`` records each step; ``close()`` does nothing."""

    def __init__(self, env) -> None:
        self.env = env
        self.frames: list[EpisodeFrame] = []

    def start(self) -> EpisodeRecorder:
        self.record()
        return self

    def step(self, action: np.ndarray, observation: np.ndarray) -> None:
        self.record()

    def close(self) -> None:
        pass

    def record(self) -> None:
        env, scene = self.env, self.env.scene
        hits = None if env.last_hits is None else np.array(env.last_hits, np.float32)
        labels = None if env.last_hits is None else np.array(env.last_labels)
        self.frames.append(EpisodeFrame(len(self.frames), tuple(scene.robot_pose()), tuple(scene.ball_positions()),
                                        tuple(scene.door_angles()), tuple(scene.box_poses()), hits, labels))

    def save_gif(self, path: str | os.PathLike, title: str = "", max_frames: int = 150, fps: float = 10.0) -> str:
        """Write the recorded episode as a GIF of at most ``max_frames`` frames (evenly
        subsampled, the last step always kept); returns the path."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.animation import PillowWriter
        from matplotlib.patches import Rectangle

        from curlnav.sim.render import draw_world

        if not self.frames:
            raise ValueError("no frames recorded: call record() after reset and after each step")
        env = self.env
        world, robot, pair = env.world, env.config.robot, env.pair
        period = env.config.control_period
        picks = np.unique(np.linspace(0, len(self.frames) - 1, min(len(self.frames), max_frames)).round().astype(int))
        trajectory = np.array([f.pose[:2] for f in self.frames])
        x0, y0, x1, y1 = world.bounds
        fig, ax = plt.subplots(figsize=(5, 5 * (y1 - y0) / max(x1 - x0, 1e-9) + 0.5), dpi=80)
        drawn: list = []  # the artists of the frame on show, removed before the next one

        def draw(frame: EpisodeFrame) -> None:
            for artist in drawn:
                artist.remove()
            before = set(ax.get_children())
            # the whole world each frame (balls, doors and boxes move); the axes and ticks stay
            draw_world(ax, world, pairs=[pair] if pair is not None else None, ball_positions=frame.balls,
                       door_angles=frame.doors, box_poses=frame.boxes)
            if frame.hits is not None:
                ax.scatter(frame.hits[:, 0], frame.hits[:, 1], s=2,
                           c=np.where(frame.labels == 1, "tab:cyan", "tab:purple"))
            ax.plot(trajectory[: frame.step + 1, 0], trajectory[: frame.step + 1, 1], "-", color="tab:green", lw=1.5)
            x, y, yaw, arm = frame.pose
            ax.add_patch(Rectangle((x - robot.base_length / 2, y - robot.base_width / 2), robot.base_length,
                                   robot.base_width, angle=math.degrees(yaw), rotation_point="center",
                                   color="tab:olive", alpha=0.9))
            tip = robot.base_length / 2 + arm
            ax.plot([x, x + tip * math.cos(yaw)], [y, y + tip * math.sin(yaw)], color="black", lw=2)
            ax.set_title(f"{title}\nt = {frame.step * period:.1f} s".strip(), fontsize=8)
            drawn[:] = [a for a in ax.get_children() if a not in before]

        writer = PillowWriter(fps=fps)
        try:
            with writer.saving(fig, os.fspath(path), dpi=fig.dpi):
                for index in picks:
                    draw(self.frames[int(index)])
                    writer.grab_frame()
        finally:
            plt.close(fig)
        return os.fspath(path)
