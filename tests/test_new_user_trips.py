"""What a new user tripped on, by what they ran: ``worlds import-sdf`` on a BARN world as it is
vendored (``.world.xz``) and what it says of start/goal pairs, a robot profile with a key it does
not know, the help's word for where the real maps come from, and a sensor-noise preset or
override that does not exist. Each refusal is one line on stderr, exit 2, naming what to type."""

from __future__ import annotations

import dataclasses
import lzma

import numpy as np
import pytest
from conftest import assert_one_line_error, run_curlnav

from curlnav.sim.config import ConfigError, RobotConfig, SensorNoiseConfig
from curlnav.sim.robots import LIDAR_KEYS
from curlnav.worlds.barn_challenge import barn
from curlnav.worlds.core.world import load_world
from curlnav.worlds.real.real_maps import MAX_PACKED_BYTES
from curlnav.worlds.real.sdf import MAX_SDF_BYTES, SdfError, read_sdf, world_from_sdf

pytestmark = pytest.mark.slow  # each test runs the command line in a process of its own


def _packed_barn_world(n: int):
    return barn.DATA / "worlds" / f"world_{n}.world.xz"


# -- 1. import-sdf reads a packed world -----------------------------------------------------------
def test_import_sdf_reads_a_vendored_barn_world_xz_as_it_is(tmp_path):
    packed = _packed_barn_world(8)
    result = run_curlnav("worlds", "import-sdf", str(packed), "--out", str(tmp_path / "w8.yaml"))
    assert result.returncode == 0, result.stderr
    assert f"0 boxes and {barn.lattice(8).sum()} cylinders" in result.stdout
    plain = tmp_path / "world_8.world"
    plain.write_bytes(barn.world_file(8))
    unpacked, _ = world_from_sdf(plain)
    assert np.array_equal(load_world(tmp_path / "w8.yaml").occupancy, unpacked.occupancy)
    # without --out: beside the file, named without .world.xz
    copy = tmp_path / "copy" / "world_8.world.xz"
    copy.parent.mkdir()
    copy.write_bytes(packed.read_bytes())
    result = run_curlnav("worlds", "import-sdf", str(copy))
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "copy" / "world_8.yaml").is_file() and (tmp_path / "copy" / "world_8.pgm").is_file()


def test_a_packed_world_is_read_under_the_caps_of_the_vendored_xz_files(tmp_path):
    """The real maps' caps: at most MAX_PACKED_BYTES packed, one whole xz stream, and (the SDF
    cap) at most MAX_SDF_BYTES unpacked, decompressed incrementally."""
    bomb = tmp_path / "bomb.world.xz"
    bomb.write_bytes(lzma.compress(b"<sdf>" + b" " * MAX_SDF_BYTES + b"</sdf>"))
    assert bomb.stat().st_size < 10_000
    with pytest.raises(SdfError, match=f"decompresses to more than {MAX_SDF_BYTES >> 20} MiB "
                                       r"\(a Gazebo SDF file's cap\)"):
        read_sdf(bomb)
    big = tmp_path / "big.world.xz"
    big.write_bytes(b"\0" * (MAX_PACKED_BYTES + 1))
    with pytest.raises(SdfError, match="packed Gazebo SDF file above"):
        read_sdf(big)
    cut = tmp_path / "cut.world.xz"
    cut.write_bytes(_packed_barn_world(8).read_bytes()[:-40])
    line = assert_one_line_error(run_curlnav("worlds", "import-sdf", str(cut), "--out", str(tmp_path / "c.yaml")),
                                 str(cut), "not a whole xz file")
    assert "XML" not in line and not (tmp_path / "c.yaml").exists()


# -- 2. what import-sdf says of pairs agrees with what eval does --------------------------------
def test_import_sdf_says_eval_draws_random_pairs_on_the_world_and_it_does(tmp_path):
    from curlnav.evaluation.compare import episode_pairs

    result = run_curlnav("worlds", "import-sdf", str(_packed_barn_world(8)), "--out", str(tmp_path / "w8.yaml"))
    assert result.returncode == 0, result.stderr
    said = " ".join(result.stdout.split())
    assert "start/goal pairs: none of its own, so curlnav eval, train and rollout draw seeded random ones" in said
    assert "pairs: [{name: p1, x: X, y: Y, yaw: 0, gx: GX, gy: GY}]" in said  # how to add fixed ones
    assert "add them to train or evaluate" not in said and not result.stderr
    world = load_world(tmp_path / "w8.yaml")
    pairs = episode_pairs(world, pairs=5)  # what curlnav eval --world w8.yaml --pairs 5 runs
    assert not world.pairs and len(pairs) == 5 and len({(p.x, p.y, p.gx, p.gy) for p in pairs}) == 5


# -- 3. a robot profile's keys, lidar included --------------------------------------------------
def test_a_robot_profile_with_an_unknown_key_is_told_every_key_lidar_included(tmp_path):
    bad = tmp_path / "mybot.yaml"
    bad.write_text("name: mybot\nbase_width: 0.5\nwheel_base: 0.4\nlidar: {beams: 100}\n")
    line = assert_one_line_error(run_curlnav("eval", "dwa", "--robot", str(bad)), str(bad), "unknown key wheel_base",
                                 f"lidar ({', '.join(LIDAR_KEYS)})")
    for field in dataclasses.fields(RobotConfig):
        assert field.name in line, field.name
    bad.write_text("name: mybot\nlidar: {beams: 100, range: 8}\n")
    assert_one_line_error(run_curlnav("eval", "dwa", "--robot", str(bad)), "unknown lidar key range",
                          f"known: {', '.join(LIDAR_KEYS)}")


# -- 4. the help says where the maps come from ---------------------------------------------------
def test_eval_help_says_the_real_maps_are_downloaded_and_the_barn_worlds_vendored():
    result = run_curlnav("eval", "--help")
    assert result.returncode == 0, result.stderr
    text = " ".join(result.stdout.split())
    real = text[text.index("real: nine real buildings"):text.index("barn: the BARN Challenge")]
    assert "downloaded once by scripts/vendor-real-maps.py" in real and "vendored" not in real
    assert "barn: the BARN Challenge's 300 worlds (vendored: in the repository)" in text
    assert len(list((barn.DATA / "worlds").glob("world_*.world.xz"))) == barn.COUNT  # they are here


# -- 5. a sensor-noise refusal names the option -------------------------------------------------
@pytest.mark.parametrize("args, fragments", [
    (["--sensor-noise", "loud"], ["--sensor-noise: unknown preset 'loud'; presets: none, realistic, harsh"]),
    (["--sensor-set", "speed=2"], ["--sensor-set: unknown field 'speed'; fields: range_sigma", "heading, randomise"]),
    (["--sensor-set", "range_sigma=-1"], ["--sensor-set 'range_sigma=-1': range_sigma must be in [0, 1]"]),
    (["--sensor-set", "dropout"], ["--sensor-set takes FIELD=VALUE"]),
    (["--suite", "barn", "--sensor-noise", "loud"], ["--sensor-noise: unknown preset 'loud'"]),
])
def test_a_bad_sensor_noise_option_is_named_in_its_refusal(args, fragments):
    line = assert_one_line_error(run_curlnav("eval", "dwa", *args), *fragments)
    assert "sensor_noise." not in line


def test_the_library_still_names_the_config_field():
    with pytest.raises(ConfigError, match="sensor_noise.preset must be one of none, realistic"):
        SensorNoiseConfig(preset="loud")
    with pytest.raises(ConfigError, match=r"sensor_noise.dropout must be in \[0, 1\]"):
        SensorNoiseConfig.from_preset("realistic", dropout=2.0)
