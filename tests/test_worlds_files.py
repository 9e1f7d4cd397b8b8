"""World files: the ROS map_server format plus curlnav's keys."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from curlnav.sim import NamoEnv, WorldError, get_world, load_world, save_world
from curlnav.sim.geometry import merge_cells_into_rectangles


def test_save_and_load_round_trip_keeps_grid_objects_and_pairs(tmp_path):
    world = get_world("door-corridor")
    for fmt in ("pgm", "png"):
        path = save_world(world, tmp_path / fmt / "corridor.yaml", image_format=fmt)
        assert (path.parent / f"corridor.{fmt}").exists()
        loaded = load_world(path)
        assert np.array_equal(loaded.occupancy, world.occupancy)
        assert loaded.resolution == world.resolution and loaded.origin == world.origin
        assert loaded.doors == world.doors and loaded.pairs == world.pairs


def test_a_plain_ros_map_loads_with_unknown_space_as_obstacle(tmp_path):
    from PIL import Image

    # ROS convention: 254 free, 0 occupied, 205 unknown; top image row is the largest y.
    pixels = np.full((4, 6), 254, dtype=np.uint8)
    pixels[0, :] = 0  # top row occupied
    pixels[3, 5] = 205  # bottom-right unknown
    Image.fromarray(pixels).save(tmp_path / "lab.pgm")
    (tmp_path / "lab.yaml").write_text(textwrap.dedent("""\
        image: lab.pgm
        resolution: 0.5
        origin: [-1.0, -2.0, 0.0]
        negate: 0
        occupied_thresh: 0.65
        free_thresh: 0.196
    """))
    world = load_world(tmp_path / "lab.yaml")
    assert world.occupancy.shape == (4, 6)
    assert world.occupancy[3].all(), "the image's top row is the map's last row"
    assert world.occupancy[0, 5], "unknown space is treated as an obstacle"
    assert world.occupancy.sum() == 7
    assert world.is_occupied(-1.0 + 0.25, -2.0 + 3.75) and not world.is_occupied(-0.75, -1.75)
    assert world.balls == () and world.pairs == ()


def _write(tmp_path, text, image=True):
    from PIL import Image

    if image:
        Image.fromarray(np.full((20, 20), 254, dtype=np.uint8)).save(tmp_path / "m.pgm")
    path = tmp_path / "w.yaml"
    path.write_text(textwrap.dedent(text))
    return path


@pytest.mark.parametrize("body, message", [
    ("image: m.pgm\nresolution: [0.1\n", "not valid YAML"),
    ("image: m.pgm\norigin: [0, 0, 0]\n", "missing required key 'resolution'"),
    ("image: nothere.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n", "does not exist"),
    ("image: m.pgm\nresolution: -1\norigin: [0, 0, 0]\n", "resolution must be a positive"),
    ("image: m.pgm\nresolution: 0.1\norigin: [0, 0, 0]\nballs: [{x: 1, y: 1, colour: red}]\n", "balls\\[0\\] has unknown keys"),
    ("image: m.pgm\nresolution: 0.1\norigin: [0, 0, 0]\ndoors: [{hinge_x: 1, hinge_y: 1, swing: up}]\n", "swing must be"),
    ("image: m.pgm\nresolution: 0.1\norigin: [0, 0, 0]\npairs: [{name: a, x: 0.5, y: 0.5, yaw: 0, gx: 5.0, gy: 0.5}]\n",
     "pair 'a' goal .* outside the map"),
])
def test_malformed_world_files_name_the_file_and_the_fault(tmp_path, body, message):
    path = _write(tmp_path, body)
    with pytest.raises(WorldError, match=message) as info:
        load_world(path)
    assert str(path) in str(info.value)


def test_a_pair_inside_an_obstacle_is_rejected_with_its_name(tmp_path):
    from PIL import Image

    pixels = np.full((20, 20), 254, dtype=np.uint8)
    pixels[5:10, 5:10] = 0
    Image.fromarray(pixels).save(tmp_path / "m.pgm")
    path = tmp_path / "w.yaml"
    path.write_text("image: m.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n"
                    "pairs: [{name: blocked, x: 0.7, y: 1.3, yaw: 0, gx: 1.5, gy: 1.5}]\n")
    with pytest.raises(WorldError, match="pair 'blocked' start .* inside an obstacle"):
        load_world(path)


def test_an_unreadable_image_is_a_clear_error(tmp_path):
    (tmp_path / "m.pgm").write_bytes(b"not an image")
    path = _write(tmp_path, "image: m.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n", image=False)
    with pytest.raises(WorldError, match="unreadable"):
        load_world(path)


def test_merged_rectangles_cover_exactly_the_obstacle_cells():
    rng = np.random.default_rng(0)
    grid = rng.random((40, 50)) < 0.3
    rects = merge_cells_into_rectangles(grid)
    covered = np.zeros_like(grid, dtype=int)
    for iy, ix, h, w in rects:
        covered[iy:iy + h, ix:ix + w] += 1
    assert np.array_equal(covered, grid.astype(int)), "every obstacle cell once, no free cell"
    assert len(rects) < grid.sum()


def test_a_world_loaded_from_file_runs_in_the_environment(tmp_path):
    path = save_world(get_world("door-corridor"), tmp_path / "corridor.yaml")
    env = NamoEnv(str(path))
    try:
        _, info = env.reset(seed=0)
        assert info["world"] == "door-corridor" and info["pair"] == "through-door"
        env.step([0.5, 0.0, 0.5])
    finally:
        env.close()


@pytest.mark.slow
def test_rollout_command_draws_a_picture(tmp_path):
    result = subprocess.run([sys.executable, "-m", "curlnav.cli", "rollout", "--world", "door-corridor",
                             "--out", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "reached the goal" in result.stdout
    pictures = list(tmp_path.glob("*.png"))
    assert len(pictures) == 1 and pictures[0].stat().st_size > 10_000


@pytest.mark.slow
def test_rollout_command_rejects_an_unknown_world_in_one_line(tmp_path):
    result = subprocess.run([sys.executable, "-m", "curlnav.cli", "rollout", "--world", "atlantis",
                             "--out", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert "unknown world 'atlantis'" in result.stderr and "Traceback" not in result.stderr
