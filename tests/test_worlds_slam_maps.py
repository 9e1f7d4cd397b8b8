"""Real SLAM maps as users have them: ROS map_server YAML + PGM/PNG with no curlnav keys,
rotated origins, the three map_server modes, random pairs, balls scattered on paths."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from curlnav.cli import main
from curlnav.sim import NamoEnv, WorldError, load_world, save_world
from curlnav.worlds.core.pairs import PairSampler, check_pairs_possible, footprint_cells, sample_pairs
from curlnav.worlds.core.world import map_server_values

ROOT = Path(__file__).resolve().parents[1]
BARN_3X3 = ROOT / "scheduler" / "curricula" / "worlds" / "barn-3x3-0.yaml"


def write_map(folder: Path, pixels: np.ndarray, origin=(0.0, 0.0, 0.0), resolution: float = 0.1,
              name: str = "lab", extra: str = "", image_name: str | None = None) -> Path:
    """A plain map_server map (no curlnav keys); ``pixels`` top row first, as ROS stores it."""
    image_name = image_name or f"{name}.pgm"
    Image.fromarray(pixels).save(folder / image_name)
    path = folder / f"{name}.yaml"
    path.write_text(f"image: {image_name}\nresolution: {resolution}\norigin: [{origin[0]}, {origin[1]}, {origin[2]}]\n"
                    f"negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n{extra}")
    return path


def walled_room(rows: int = 60, cols: int = 100) -> np.ndarray:
    pixels = np.full((rows, cols), 254, dtype=np.uint8)
    pixels[0, :] = pixels[-1, :] = 0
    pixels[:, 0] = pixels[:, -1] = 0
    return pixels


# -- rotated origins ---------------------------------------------------------------------
@pytest.mark.parametrize("yaw", [3.14, -1.57])
def test_a_rotated_map_loads_and_a_known_obstacle_pixel_lands_where_ros_puts_it(tmp_path, yaw):
    pixels = walled_room(40, 60)
    pixels[9, 20] = 0  # image row 9 from the top of 40 -> grid row 30, column 20
    ox, oy = 1.5, -2.0
    world = load_world(write_map(tmp_path, pixels, origin=(ox, oy, yaw)))
    assert world.origin == (ox, oy) and world.origin_yaw == pytest.approx(yaw)
    assert world.occupancy[30, 20]
    # ROS: a cell's map position is origin + R(yaw) (cell centre in the grid frame)
    u, v = (20 + 0.5) * 0.1, (30 + 0.5) * 0.1
    x = ox + math.cos(yaw) * u - math.sin(yaw) * v
    y = oy + math.sin(yaw) * u + math.cos(yaw) * v
    assert world.cell_centre(30, 20) == pytest.approx((x, y))
    assert world.cell_of(x, y) == (30, 20) and world.is_occupied(x, y)
    # the unrotated reading of the same numbers would be somewhere else entirely
    assert math.hypot(x - (ox + u), y - (oy + v)) > 1.0
    # map -> grid -> map round trip, and the bounds hold every corner
    gx, gy = world.grid_from_map(x, y)
    assert world.map_from_grid(gx, gy) == pytest.approx((x, y))
    x0, y0, x1, y1 = world.bounds
    for cx, cy in world.corners():
        assert x0 - 1e-9 <= cx <= x1 + 1e-9 and y0 - 1e-9 <= cy <= y1 + 1e-9


@pytest.mark.parametrize("yaw", [3.14, -1.57])
def test_save_writes_the_origin_yaw_back_and_pairs_round_trip(tmp_path, yaw):
    world = load_world(write_map(tmp_path, walled_room(), origin=(2.0, -1.0, yaw)))
    pair = sample_pairs(world, 1, seed=4)[0]
    world = world.with_changes(pairs=(pair,))
    saved = save_world(world, tmp_path / "out" / "rot.yaml")
    meta = yaml.safe_load(saved.read_text())
    assert meta["origin"][2] == pytest.approx(yaw) and meta["mode"] == "trinary"
    loaded = load_world(saved)
    assert loaded.origin_yaw == pytest.approx(yaw) and loaded.origin == world.origin
    assert np.array_equal(loaded.occupancy, world.occupancy)
    assert loaded.pairs == (pair,)
    assert not loaded.is_occupied(pair.x, pair.y) and not loaded.is_occupied(pair.gx, pair.gy)


# -- map_server modes --------------------------------------------------------------------
def test_trinary_scale_and_raw_give_the_map_server_values_and_free_means_value_zero(tmp_path):
    # grey levels: 0 black, 100, 205 (ROS unknown), 230, 254 white; plus 50 for raw
    row = np.array([0, 50, 100, 205, 230, 254], dtype=np.uint8)
    img = Image.fromarray(row[None, :])
    # occ = 1 - shade: 1.0, .80, .61, .196, .098, .004
    assert map_server_values(img, "trinary").tolist() == [[100, 100, -1, -1, 0, 0]]
    scale = map_server_values(img, "scale")[0].tolist()
    assert scale[:2] == [100, 100] and scale[4:] == [0, 0]
    assert scale[2] == round((1 - 100 / 255 - 0.196) / (0.65 - 0.196) * 100) and scale[3] == 0  # 205: occ == 0.196
    # raw: the grey level itself when 0..100, else unknown; negate and thresholds ignored (Nav2)
    assert map_server_values(img, "raw").tolist() == [[0, 50, 100, -1, -1, -1]]
    assert map_server_values(img, "raw", negate=True).tolist() == [[0, 50, 100, -1, -1, -1]]
    assert map_server_values(img, "trinary", negate=True).tolist() == [[0, -1, -1, 100, 100, 100]]
    # files: one image, three modes; our grid is free exactly where map_server says 0
    for mode, free in (("trinary", [0, 0, 0, 0, 1, 1]), ("scale", [0, 0, 0, 1, 1, 1]), ("raw", [1, 0, 0, 0, 0, 0])):
        world = load_world(write_map(tmp_path, row[None, :], name=f"m-{mode}", extra=f"mode: {mode}\n"))
        assert (~world.occupancy[0]).astype(int).tolist() == free, mode


def test_alpha_is_averaged_in_for_trinary_and_means_unknown_for_scale(tmp_path):
    rgba = np.zeros((1, 3, 4), dtype=np.uint8)
    rgba[0, 0] = (254, 254, 254, 255)  # opaque white: free in both
    rgba[0, 1] = (254, 254, 254, 0)  # transparent white: trinary shade (3*254+0)/4 -> occ .25 unknown; scale unknown
    rgba[0, 2] = (254, 254, 254, 200)  # half-transparent white: trinary occ .06 free; scale unknown (not opaque)
    img = Image.fromarray(rgba, mode="RGBA")
    assert map_server_values(img, "trinary").tolist() == [[0, -1, 0]]
    assert map_server_values(img, "scale").tolist() == [[0, -1, -1]]
    img.save(tmp_path / "a.png")
    (tmp_path / "a.yaml").write_text("image: a.png\nresolution: 0.1\norigin: [0, 0, 0]\nnegate: 0\n"
                                     "occupied_thresh: 0.65\nfree_thresh: 0.196\nmode: scale\n")
    assert load_world(tmp_path / "a.yaml").occupancy.tolist() == [[False, True, True]]


def test_an_unknown_mode_is_refused_naming_the_file_and_the_field(tmp_path):
    path = write_map(tmp_path, walled_room(), extra="mode: fuzzy\n")
    with pytest.raises(WorldError, match="mode must be one of trinary, scale, raw") as info:
        load_world(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


# -- random pairs on plain maps ----------------------------------------------------------
def test_a_plain_map_yields_seeded_connected_pairs_at_least_the_minimum_apart(tmp_path):
    pixels = walled_room(60, 100)
    pixels[:45, 50:52] = 0  # a wall from the top, a gap at the bottom: the two halves connect
    world = load_world(write_map(tmp_path, pixels, origin=(2.0, -1.0, 3.14)))
    sampler = check_pairs_possible(world)
    assert sampler is not None and sampler.spec.min_distance == pytest.approx(4.0)
    first = sample_pairs(world, 8, seed=11)
    assert first == sample_pairs(world, 8, seed=11)
    assert first != sample_pairs(world, 8, seed=12)
    for pair in first:
        assert pair.distance >= 4.0 - 1e-9
        start, goal = world.cell_of(pair.x, pair.y), world.cell_of(pair.gx, pair.gy)
        assert sampler.labels[start] and sampler.labels[start] == sampler.labels[goal]
    # the environment draws the same way from its seed, before and without any assigned pair
    env = NamoEnv(world)
    try:
        env.np_random = np.random.default_rng(5)
        a = env._draw_pair()
        env.np_random = np.random.default_rng(5)
        assert env._draw_pair() == a
    finally:
        env.close()


def test_a_small_plain_map_shrinks_the_minimum_distance_to_fit(tmp_path):
    world = load_world(write_map(tmp_path, walled_room(40, 40)))  # 4 m x 4 m room
    sampler = PairSampler(world)
    assert 1.0 <= sampler.spec.min_distance < 4.0
    assert all(p.distance >= sampler.spec.min_distance for p in sample_pairs(world, 5, seed=0))


def test_a_map_with_no_connected_free_space_fails_in_one_line_before_any_scene(tmp_path, monkeypatch):
    import curlnav.sim.env as env_module

    def no_scene(*args, **kwargs):
        raise AssertionError("the PyBullet scene must not be built for a map with no free space")

    monkeypatch.setattr(env_module, "Scene", no_scene)
    monkeypatch.setattr(env_module, "connect", no_scene)
    path = write_map(tmp_path, walled_room(12, 12))  # 1.2 m square: no room for the robot anywhere
    with pytest.raises(WorldError, match="no connected free space") as info:
        NamoEnv(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)
    assert main(["rollout", "--world", str(path), "--steps", "2", "--out", str(tmp_path / "r")]) == 2


def test_drawn_starts_leave_the_robot_footprint_free_at_its_yaw():
    world = load_world(BARN_3X3)
    env = NamoEnv(world)
    try:
        robot = env.config.robot
        rows, cols = world.occupancy.shape
        for seed in range(200):
            env.np_random = np.random.default_rng(seed)
            pair = env._draw_pair()
            cells = footprint_cells(world, pair.x, pair.y, pair.yaw, robot.base_length, robot.base_width)
            assert len(cells) > 0
            assert ((cells >= 0) & (cells < (rows, cols))).all()
            assert not world.occupancy[cells[:, 0], cells[:, 1]].any(), f"seed {seed}: start {pair} touches a wall"
            assert pair.distance >= world.random_pairs.min_distance
    finally:
        env.close()


# -- balls on shortest paths -------------------------------------------------------------
def test_scatter_balls_puts_n_balls_on_free_cells_near_the_shortest_paths(tmp_path):
    from curlnav.worlds.difficulty.rank import path_points, world_paths
    from curlnav.worlds.procedural.scatter import scatter_balls

    pixels = walled_room(60, 120)
    pixels[:40, 60:62] = 0
    world = load_world(write_map(tmp_path, pixels, origin=(0.0, 0.0, -1.57)))
    task = scatter_balls(world, 6, seed=3, radius=0.25, pairs=2)
    assert len(task.balls) == 6 and len(task.pairs) == 2
    again = scatter_balls(world, 6, seed=3, radius=0.25, pairs=2)
    assert again.balls == task.balls and again.pairs == task.pairs
    _, paths = world_paths(task)
    points = np.concatenate([np.stack(path_points(task, p), axis=1) for p in paths])
    for i, ball in enumerate(task.balls):
        assert np.hypot(points[:, 0] - ball.x, points[:, 1] - ball.y).min() < 0.11, "on a path"
        for angle in np.linspace(0, 2 * math.pi, 16, endpoint=False):  # the whole disc is free
            assert not world.is_occupied(ball.x + ball.radius * math.cos(angle), ball.y + ball.radius * math.sin(angle))
        for other in task.balls[i + 1:]:
            assert math.hypot(ball.x - other.x, ball.y - other.y) >= 2 * ball.radius
    out = tmp_path / "task.yaml"
    assert main(["worlds", "scatter-balls", str(tmp_path / "lab.yaml"), "--count", "4", "--seed", "1",
                 "--out", str(out)]) == 0
    written = load_world(out)
    assert len(written.balls) == 4 and written.pairs and written.origin_yaw == pytest.approx(-1.57)


# -- the commands on a plain rotated map -------------------------------------------------
@pytest.mark.slow
def test_worlds_show_rollout_and_eval_work_on_a_plain_rotated_map(tmp_path, capsys):
    pixels = walled_room(50, 80)
    pixels[:30, 40] = 0
    path = write_map(tmp_path, pixels, origin=(-3.0, 4.0, 3.14))
    picture = tmp_path / "show.png"
    assert main(["worlds", "show", str(path), "--out", str(picture)]) == 0
    assert picture.exists() and "5 pairs (seeded random" in capsys.readouterr().out
    assert main(["rollout", "--world", str(path), "--steps", "5", "--out", str(tmp_path / "roll")]) == 0
    assert len(list((tmp_path / "roll").glob("*.png"))) == 1
    # eval with a freshly initialised artefact: the held-out pairs are drawn on the plain map
    result = subprocess.run([sys.executable, "-c", textwrap.dedent(f"""
        from curlnav.learner.artefact import export_policy
        from curlnav.config import D4PGConfig
        from curlnav.learner.d4pg import init_state
        from curlnav.layout import ObservationLayout
        from curlnav.sim import EnvConfig
        cfg = EnvConfig()
        state = init_state(D4PGConfig(seed=0), ObservationLayout.from_env_config(cfg), "cpu")
        export_policy(state, {str(tmp_path / 'policy')!r}, cfg, worlds=["lab"])
        """)], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-2000:]
    assert main(["eval", str(tmp_path / "policy"), "--world", str(path), "--episodes", "1"]) == 0
    assert "success" in capsys.readouterr().out


def test_naming_the_same_map_file_again_at_reset_keeps_the_built_scene(tmp_path):
    path = write_map(tmp_path, walled_room(), origin=(0.0, 0.0, 3.14))
    env = NamoEnv(path)
    try:
        env.reset(seed=0, options={"world": str(path)})
        scene = env.scene
        env.reset(seed=1, options={"world": str(path)})
        assert env.scene is scene, "a large SLAM map must not be rebuilt every episode"
        env.reset(seed=2, options={"world": "open-room"})
        assert env.world.name == "open-room" and env.scene is not scene
    finally:
        env.close()
