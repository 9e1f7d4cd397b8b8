"""Issue 55, the files and arguments a user is handed: artefact metadata read for the deploy line,
robot profiles, numbers on the command line and in files, duplicate keys. Each probe ends in one
``curlnav: error:`` line (or argparse's usage error) with exit 2, within 10 s and 500 MB.

The vendoring script, the vendored maps' ``.xz`` files and ``worlds import-sdf`` have their own
test modules (``test_vendor_real_maps_hostile.py``, ``test_worlds_real_maps.py``,
``test_worlds_sdf_hostile.py``)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from conftest import ROOT, assert_one_line_error
from conftest import run_capped as curlnav

from curlnav.cli import main
from curlnav.files import FileRefused, decimal_float, decimal_int, loads_json, loads_yaml, read_yaml
from curlnav.nav import deploy_notice, deploy_stack
from curlnav.sim.config import ConfigError, SensorNoiseConfig
from curlnav.sim.robots import load_profile


def artefact_with(tmp_path: Path, metadata: bytes | None = None, deploy=None) -> Path:
    """A copy of ``policies/barn-jackal`` whose ``metadata.json`` is ``metadata`` (or its own with
    ``deploy`` set)."""
    folder = tmp_path / "artefact"
    shutil.copytree(ROOT / "policies" / "barn-jackal", folder)
    if metadata is None:
        meta = json.loads((folder / "metadata.json").read_text())
        meta["deploy"] = deploy
        metadata = json.dumps(meta).encode()
    (folder / "metadata.json").write_bytes(metadata)
    return folder


# -- artefact metadata read for the deploy line ------------------------------------------------
@pytest.mark.slow
def test_a_metadata_json_nested_100000_deep_is_refused_in_one_line_not_a_recursion_traceback(tmp_path):
    folder = artefact_with(tmp_path, b"[" * 100_000 + b"]" * 100_000)
    result, peak_mb, wall_s = curlnav("eval", str(folder), "--suite", "barn", "--worlds", "0")
    assert_one_line_error(result, "metadata.json", "nested too deep")
    assert wall_s < 10 and peak_mb < 500, (wall_s, peak_mb)


@pytest.mark.slow
def test_a_200_mb_metadata_json_is_refused_at_its_size_cap_without_being_read_whole(tmp_path):
    folder = artefact_with(tmp_path, b"")
    with open(folder / "metadata.json", "wb") as f:
        f.truncate(200 << 20)  # 200 MB (sparse: the test's disk stays free)
    result, peak_mb, wall_s = curlnav("eval", str(folder), "--suite", "barn", "--worlds", "0")
    assert_one_line_error(result, "metadata.json", "above 4096 KiB")
    assert wall_s < 10 and peak_mb < 500, (wall_s, peak_mb)


@pytest.mark.parametrize("deploy", ["+rescue+shield\n", "+rescue+shield\r", "\n", "+shield "])
def test_a_deploy_stack_with_a_trailing_newline_or_blank_is_refused(tmp_path, deploy):
    folder = artefact_with(tmp_path, deploy=deploy)
    with pytest.raises(ValueError, match="deploy must be suffixes"):
        deploy_stack(str(folder))


def test_the_shipped_deploy_stacks_are_still_read(tmp_path):
    assert deploy_stack(str(artefact_with(tmp_path, deploy="+rescue+shield"))) == "+rescue+shield"
    assert deploy_stack(str(ROOT / "policies" / "namo-robust")) == "+rescue+shield+scan-match"


def test_a_folder_named_like_a_planner_does_not_make_eval_say_the_planner_drives_as_an_artefact(
        tmp_path, monkeypatch, capsys):
    folder = artefact_with(tmp_path, deploy="+rescue+shield")
    shutil.move(folder, tmp_path / "dwa")
    monkeypatch.chdir(tmp_path)
    assert deploy_stack("dwa") == "" and deploy_notice("dwa", "dwa+bare") == ""
    assert main(["eval", "dwa", "--world", "open-room", "--pairs", "1"]) == 0
    assert "driven as its artefact ships it" not in capsys.readouterr().out


# -- robot profiles ----------------------------------------------------------------------------
@pytest.mark.parametrize("line, field", [
    ("base_length: 1e300", "base_length must be at most 5"),
    ("base_length: 1000", "base_length must be at most 5"),
    ("max_linear_speed: 1e300", "max_linear_speed must be at most 10"),
    ("max_angular_speed: 1e300", "max_angular_speed must be at most 10"),
    ("base_mass: 1e300", "base_mass must be at most 2000"),
    ("drive_force: 1e300", r"drive_force must be at most 1e\+06"),
    ("lidar: {range_m: 1.0e300}", "lidar_max_range must be at most 100"),
    ("lidar: {fov_deg: 1.0e-300}", "lidar_fov must be at least 1 degree"),
    ("lidar: {height_m: 1000}", "lidar_height must be at most 5"),
])
def test_a_robot_profile_beyond_a_robot_s_bounds_is_refused_naming_the_field_and_its_limit(tmp_path, line, field):
    profile = tmp_path / "bot.yaml"
    profile.write_text(f"name: bot\n{line}\n")
    with pytest.raises(ConfigError, match=field) as caught:
        load_profile(str(profile))
    assert str(profile) in str(caught.value) and "\n" not in str(caught.value)


def test_a_robot_profile_within_bounds_still_loads(tmp_path):
    profile = tmp_path / "bot.yaml"
    profile.write_text("name: bot\nbase_length: 1.2\nmax_linear_speed: 1.5e0\nlidar: {range_m: 30, fov_deg: 360}\n")
    loaded = load_profile(str(profile))
    assert loaded.robot.base_length == 1.2 and loaded.robot.max_linear_speed == 1.5 and loaded.lidar_max_range == 30


def test_a_duplicate_key_in_a_robot_profile_is_refused_not_silently_the_last_value(tmp_path, capsys):
    profile = tmp_path / "bot.yaml"
    profile.write_text("name: bot\nbase_length: 0.9\nbase_length: 2\n")
    assert main(["eval", "dwa", "--robot", str(profile), "--world", "open-room", "--pairs", "1"]) == 2
    err = capsys.readouterr().err
    assert "bot.yaml" in err and "'base_length' is given twice" in err and len(err.splitlines()) == 1


# -- numbers ---------------------------------------------------------------------------------------
def test_empty_worlds_is_refused_instead_of_running_all_300_barn_worlds(capsys):
    assert main(["eval", "dwa", "--suite", "barn", "--worlds="]) == 2
    assert "--worlds takes A-B or N" in capsys.readouterr().err


@pytest.mark.parametrize("worlds", ["0_1", "\u0661", "0-\u0662", "1e0"])
def test_barn_world_numbers_are_ascii_decimal_only(worlds, capsys):
    assert main(["eval", "dwa", "--suite", "barn", f"--worlds={worlds}"]) == 2
    assert "--worlds" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["0_1", "\u0661", "1e0", "0x1"])
def test_command_line_numbers_are_ascii_decimal_only(value, capsys):
    with pytest.raises(SystemExit) as caught:
        main(["eval", "dwa", "--world", "open-room", "--pairs", value])
    assert caught.value.code == 2 and "--pairs" in capsys.readouterr().err


@pytest.mark.parametrize("item", ["dropout=0_1", "dropout=\u0660.1", "latency_steps=0_1", "latency_steps=\u0661",
                                  "range_sigma=nan", "range_sigma=1e400"])
def test_sensor_set_numbers_are_ascii_decimal_only(item):
    with pytest.raises(ConfigError, match=item.split("=")[0]):
        SensorNoiseConfig.from_strings("realistic", [item])


def test_sensor_set_still_takes_decimal_numbers():
    noise = SensorNoiseConfig.from_strings("realistic", ["dropout=0.1", "latency_steps=2", "range_sigma=2e-2"])
    assert (noise.dropout, noise.latency_steps, noise.range_sigma) == (0.1, 2, 0.02)


def test_decimal_parsers_refuse_what_python_s_int_and_float_take():
    for text in ("0_1", "\u0661", "1 000", "0x1f", "٣"):
        with pytest.raises(ValueError):
            decimal_int(text)
    for text in ("0_1.5", "nan", "inf", "1e400", "\u0661.5", "1_0"):
        with pytest.raises(ValueError):
            decimal_float(text)
    assert (decimal_int("-12"), decimal_float("2.5e-3"), decimal_float(".5")) == (-12, 0.0025, 0.5)


@pytest.mark.parametrize("text", ["a: 0_1", "a: 0x1f", "a: 1:30", "a: 010", "a: 1_000.0", "a: \u0661"])
def test_yaml_numbers_in_other_spellings_are_not_numbers(text):
    """YAML 1.1 reads ``0_1`` as 1 and ``1:30`` as 90; here they stay text, which a field refuses."""
    assert isinstance(loads_yaml(text)["a"], str)


def test_yaml_decimal_numbers_still_read_as_numbers():
    assert loads_yaml("a: [1, -2, 0, 1.5, 1e-3, 2.0e+2, .5, .inf]")["a"][:7] == [1, -2, 0, 1.5, 0.001, 200.0, 0.5]


def test_a_yaml_number_in_an_explicit_tag_is_decimal_only():
    with pytest.raises(FileRefused, match="not a whole number in decimal digits"):
        loads_yaml("a: !!int 0x10")


@pytest.mark.parametrize("text", ["a: 1\na: 2\n", "b: {c: 1, c: 2}\n", "- {x: 1, x: 1}\n"])
def test_a_key_given_twice_in_yaml_is_refused_naming_the_line(tmp_path, text):
    path = tmp_path / "world.yaml"
    path.write_text(text)
    with pytest.raises(FileRefused, match=r"world.yaml: not valid YAML at line \d+.*given twice"):
        read_yaml(path)


def test_a_key_given_twice_in_json_is_refused():
    with pytest.raises(FileRefused, match="metadata.json: the key 'deploy' is given twice"):
        loads_json('{"deploy": "+shield", "deploy": ""}', "metadata.json")
