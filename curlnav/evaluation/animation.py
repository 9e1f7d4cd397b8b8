"""An episode as an animated GIF: the robot, its LiDAR hits and the movable objects, step by
step, over the world drawing of ``curlnav.sim.render`` (``curlnav policy run --gif``)."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np


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
    """``record()`` after ``reset`` and after every ``step`` of ``env``; ``save_gif(path)``."""

    def __init__(self, env) -> None:
        self.env = env
        self.frames: list[EpisodeFrame] = []

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
