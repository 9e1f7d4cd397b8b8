"""The real-map suite (``curlnav eval AGENT... --suite real``): real buildings' SLAM maps, downloaded
by ``scripts/vendor-real-maps.py`` (never committed) and checked byte for byte against the committed
manifest, their sources and licences, loaded whole, unknown cells as walls, and the suite's pairs
and balls fixed by seed, reachable for the Husky, on the shortest paths. Where the maps are absent
(a fresh clone, CI: the tests need no network), the tests that read them skip. Hostile vendored
files and manifests (issue 55: truncated or bomb xz, links, malformed lines) are one-line refusals
within bounds, planted in a copy of the data folder."""

from __future__ import annotations

import hashlib
import io
import lzma
import os
import re
import resource
import time

import numpy as np
import pytest
import yaml
from PIL import Image
from scipy import ndimage

from curlnav.cli import main
from curlnav.evaluation.compare import SUITES
from curlnav.worlds.builtin import get_world
from curlnav.worlds.core.pairs import FOOTPRINT_MARGIN, HUSKY_FOOTPRINT, footprint_free
from curlnav.worlds.core.world import WorldError, map_server_values
from curlnav.worlds.difficulty.rank import path_points, world_paths
from curlnav.worlds.real import real_maps

#: kept apart for an independent check of the suite: no map may come from them
FORBIDDEN = ("turtlebot/turtlebot_apps", "utexas-bwi/bwi_common", "mit-racecar/racecar_simulator",
             "f1tenth/f1tenth_simulator", "b-it-bots/mas_domestic_robotics", "RobotnikAutomation/summit_xl_common",
             "aws-robotics/aws-robomaker-small-house-world")
OPEN_LICENCES = {"BSD", "MIT", "Apache-2.0", "CC-BY-4.0"}
SMALL = ("yujin-rnd", "jsk-eng8-6f")  # the quickest to build: the quick loop's determinism check

vendored = pytest.mark.skipif(bool(real_maps.missing()), reason="the real maps are not downloaded here "
                              "(scripts/vendor-real-maps.py writes them into curlnav/worlds/data/real)")


def manifest() -> dict[str, str]:
    """``<name>/<file>`` -> sha256 of the original bytes."""
    lines = real_maps.MANIFEST.read_text().splitlines()
    return {path: digest for digest, path in (line.split("  ", 1) for line in lines if line)}


# -- sources and licences --------------------------------------------------------------------------
def test_the_manifest_names_every_original_file_of_every_map_and_nothing_else():
    expected = {f"{m.name}/{file}" for m in real_maps.MAPS.values() for file in m.originals}
    assert set(manifest()) == expected
    assert all(re.fullmatch(r"[0-9a-f]{64}", digest) for digest in manifest().values())


@vendored
def test_the_vendored_bytes_are_the_sources_bytes():
    for path, digest in manifest().items():
        name, file = path.split("/", 1)
        assert hashlib.sha256(real_maps.original_bytes(name, file)).hexdigest() == digest, path


def test_every_source_md_names_its_repository_commit_paths_and_an_open_licence():
    assert len(real_maps.MAPS) >= 8
    for m in real_maps.MAPS.values():
        text = (m.folder / "SOURCE.md").read_text()
        assert f"https://github.com/{m.repository}" in text and m.commit in text and re.fullmatch(r"[0-9a-f]{40}", m.commit)
        assert m.image in text and m.licence_file in text and (m.yaml is None or m.yaml in text)
        assert m.licence in OPEN_LICENCES and f"Licence: {m.licence}" in text
        assert "real building" in text and m.why_real in text


def test_no_map_comes_from_a_repository_kept_apart():
    texts = [real_maps.MANIFEST.read_text()] + [(m.folder / "SOURCE.md").read_text() for m in real_maps.MAPS.values()]
    for m in real_maps.MAPS.values():
        assert m.repository.lower() not in {f.lower() for f in FORBIDDEN}, m.name
        assert not ("navigation2" in m.repository and "warehouse" in m.image.lower()), m.name
        texts.append(" ".join((m.repository, m.image, m.yaml or "", m.building, m.why_real)))
    for text in texts:
        for forbidden in FORBIDDEN:
            assert forbidden.lower() not in text.lower(), forbidden


# -- loading ---------------------------------------------------------------------------------------
@vendored
def test_every_map_loads_whole_at_a_sensible_size_and_resolution_with_unknown_cells_as_walls():
    for m in real_maps.MAPS.values():
        world = real_maps.map_world(m.name)
        rows, cols = world.occupancy.shape
        assert 0.02 <= world.resolution <= 0.1, m.name
        assert 15.0 <= cols * world.resolution <= 100.0 and 15.0 <= rows * world.resolution <= 100.0, m.name
        assert 0.03 < (~world.occupancy).mean() < 0.7, m.name
        assert world.name == f"real-{m.name}" and world.source == f"real:{m.name}"
        assert not world.pairs and not world.balls
        # whole, never cropped: the grid is the image, and map_server's unknown (-1) is an obstacle
        meta = yaml.safe_load(real_maps.original_bytes(m.name, m.yaml_name))
        with Image.open(io.BytesIO(real_maps.original_bytes(m.name, m.originals[1]))) as img:
            assert img.size == (cols, rows), m.name
            values = np.flipud(map_server_values(img, "trinary", bool(meta["negate"]), meta["occupied_thresh"],
                                                 meta["free_thresh"]))
        unknown = values == -1
        assert unknown.any(), m.name  # a SLAM map: space beyond its walls was never seen
        assert world.occupancy[unknown].all() and world.occupancy[values == 100].all(), m.name
        assert not world.occupancy[values == 0].any(), m.name


def test_an_unknown_real_map_is_one_line_naming_the_maps():
    with pytest.raises(WorldError, match="unknown real map 'atlantis'; choose from willow-garage"):
        get_world("real:atlantis")


# -- the suite -------------------------------------------------------------------------------------
def check_task(world) -> None:
    """The suite's promises for one task world (see curlnav.worlds.real.real_maps)."""
    assert [p.name for p in world.pairs] == [f"p{i + 1}" for i in range(real_maps.PAIRS)]
    assert len(world.balls) == real_maps.BALLS and all(b.region is None for b in world.balls)
    free, graph = real_maps.cspace_graph(world)
    labels, _ = ndimage.label(free, structure=np.ones((3, 3), dtype=bool))
    for pair in world.pairs:
        assert real_maps.MIN_DISTANCE <= pair.distance <= real_maps.MAX_DISTANCE, pair
        (sy, sx), (gy, gx) = world.cell_of(pair.x, pair.y), world.cell_of(pair.gx, pair.gy)
        assert free[sy, sx] and free[gy, gx] and labels[sy, sx] == labels[gy, gx], pair  # connected on the C-space grid
        assert pair.distance <= real_maps.path_length(world, graph, pair) <= real_maps.MAX_PATH_M, pair
        assert footprint_free(world, pair.x, pair.y, pair.yaw, *HUSKY_FOOTPRINT, margin=FOOTPRINT_MARGIN), pair
    # balls on the pairs' shortest paths (scatter_balls' own C-space grid), clear of walls
    _, paths = world_paths(world)
    points = np.vstack([np.column_stack(path_points(world, path)) for path in paths])
    for ball in world.balls:
        assert np.hypot(points[:, 0] - ball.x, points[:, 1] - ball.y).min() < 1e-3, ball
        assert not world.is_occupied(ball.x, ball.y)


@vendored
@pytest.mark.parametrize("name", SMALL)
def test_a_task_is_the_same_every_time_and_keeps_the_suites_promises(name):
    world = real_maps.task.__wrapped__(name)
    again = real_maps.task.__wrapped__(name)
    assert world.pairs == again.pairs and world.balls == again.balls
    assert np.array_equal(world.occupancy, again.occupancy)
    check_task(world)


@vendored
@pytest.mark.slow
def test_every_task_of_the_suite_keeps_its_promises_and_fits_the_time_limit():
    from curlnav.config import ExperimentConfig

    env = ExperimentConfig().eval_env
    reach = env.max_episode_steps * env.control_period * env.robot.max_linear_speed  # m in a trial at full speed
    assert real_maps.MAX_PATH_M <= 0.6 * reach
    for name in real_maps.MAPS:
        check_task(real_maps.task(name))


def test_the_real_suite_runs_every_map_with_its_pairs():
    suite = SUITES["real"]
    assert suite.worlds == tuple(f"real:{name}" for name in real_maps.MAPS)
    assert suite.trials == real_maps.PAIRS and suite.ball_placements == 1
    assert len(suite.about) < 400 and "unknown cells are walls" in suite.about


@vendored
def test_the_suite_runs_each_pair_once_in_order():
    world = get_world("real:yujin-rnd")
    assert world is real_maps.task("yujin-rnd")
    assert SUITES["real"].pairs_of(world) == list(world.pairs)


def test_eval_offers_the_real_suite_and_refuses_to_change_it(capsys):
    assert main(["eval", "oracle", "--suite", "real", "--pairs", "2"]) != 0
    assert "--suite real fixes the worlds" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    assert "real: nine real buildings" in " ".join(capsys.readouterr().out.split())


def test_nobody_trains_or_tunes_on_the_real_suites_maps(tmp_path):
    """A real map as the training world, a curriculum stage or a validation target is refused."""
    from curlnav.scheduler.curriculum import CurriculumError, load_curriculum
    from curlnav.worlds.core.heldout import HeldOutSeedError, check_training_world

    with pytest.raises(HeldOutSeedError, match="real:willow-garage is a map of the real suite"):
        check_training_world("real:willow-garage")
    for body in ("stages:\n  - name: S1\n    worlds: [\"real:yujin-rnd\"]\n",
                 "stages:\n  - name: S1\n    worlds: [open-room]\nevaluate:\n  - {world: \"real:yujin-rnd\"}\n"):
        path = tmp_path / "c.yaml"
        path.write_text(body)
        with pytest.raises(CurriculumError, match="real:yujin-rnd is a map of the real suite"):
            load_curriculum(path)
    assert main(["train", "--serial", "--world", "real:yujin-rnd", "--minutes", "1"]) == 2


@vendored
def test_a_downloaded_file_that_is_not_the_sources_is_refused_in_one_line(monkeypatch):
    real = real_maps.manifest()
    key = next(k for k in real if k.startswith("yujin-rnd/") and k.endswith(".pgm"))
    monkeypatch.setattr(real_maps, "manifest", lambda: {**real, key: "0" * 64})
    with pytest.raises(WorldError, match=r"real map yujin-rnd: .*\.pgm is not the source's .*vendor-real-maps.py"):
        real_maps.map_world("yujin-rnd")


# -- hostile vendored files (issue 55) -------------------------------------------------------------
@pytest.fixture
def planted(tmp_path, monkeypatch) -> real_maps.RealMap:
    """yujin-rnd's folder in a ``DATA`` of ``tmp_path``: a small valid YAML, image and licence, and a
    ``MANIFEST.sha256`` saying their sha256; the suite's task cache cleared around the test."""
    m = real_maps.MAPS["yujin-rnd"]
    data = tmp_path / "real"
    (data / m.name).mkdir(parents=True)
    yaml_name, image, licence = m.originals
    originals = {yaml_name: f"image: {image}\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
                            "occupied_thresh: 0.65\nfree_thresh: 0.196\n".encode(),
                 image: b"P5\n4 4\n255\n" + bytes(range(0, 256, 16)), licence: b"<package/>\n"}
    for file, body in originals.items():
        (data / m.name / (file + ".xz" if file == image else file)).write_bytes(
            lzma.compress(body) if file == image else body)
    (data / "MANIFEST.sha256").write_text(
        "".join(f"{hashlib.sha256(body).hexdigest()}  {m.name}/{file}\n" for file, body in originals.items()))
    monkeypatch.setattr(real_maps, "DATA", data)
    monkeypatch.setattr(real_maps, "MANIFEST", data / "MANIFEST.sha256")
    real_maps.task.cache_clear()
    assert real_maps.original_bytes(m.name, image) == originals[image]
    yield m
    real_maps.task.cache_clear()


def refusal(call, *args) -> str:
    """The one-line ``WorldError`` of ``call(*args)``, raised within a second."""
    start = time.monotonic()
    with pytest.raises(WorldError) as info:
        call(*args)
    assert time.monotonic() - start < 1.0
    message = str(info.value)
    assert "\n" not in message and len(message) < 400, message
    return message


@pytest.mark.parametrize("packed", ["empty", "truncated", "random", "bytes after its end"])
def test_a_vendored_xz_that_is_not_whole_is_one_line_naming_the_file(planted, packed):
    image = planted.originals[1]
    path = planted.folder / (image + ".xz")
    whole = path.read_bytes()
    path.write_bytes({"empty": b"", "truncated": whole[:len(whole) // 2], "random": os.urandom(4096),
                      "bytes after its end": whole + b"more"}[packed])
    assert f"{path}: not a whole xz file" in refusal(real_maps.original_bytes, planted.name, image)


@pytest.mark.parametrize("which", [0, 1, 2])
def test_a_vendored_file_that_is_a_symlink_is_refused(planted, tmp_path, which):
    file = planted.files[which]
    path = planted.folder / file
    path.rename(tmp_path / file)  # the same bytes, reached through a link
    path.symlink_to(tmp_path / file)
    message = refusal(real_maps.original_bytes, planted.name, planted.originals[which])
    assert f"{path}: not a regular file" in message


def test_an_xz_bomb_is_refused_at_the_cap_in_bounded_time_and_memory(planted):
    """The issue's bomb: 520 KB of xz that took 2.5 GB, then MemoryError. Here: 40 xz streams of
    64 MiB of zeros each (2.5 GiB in all, about 400 KB)."""
    packer = lzma.LZMACompressor(preset=0)
    stream = b"".join(packer.compress(bytes(1 << 20)) for _ in range(64)) + packer.flush()
    path = planted.folder / (planted.originals[1] + ".xz")
    path.write_bytes(stream * 40)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    start = time.monotonic()
    with pytest.raises(WorldError) as info:
        real_maps.original_bytes(planted.name, planted.originals[1])
    assert time.monotonic() - start < 3.0
    grown_mib = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert grown_mib < 300, f"the peak grew by {grown_mib:.0f} MiB"
    cap = real_maps.MAX_IMAGE_BYTES
    assert str(info.value) == f"{path}: decompresses to more than {cap >> 20} MiB (a map image's cap); refused"
    assert cap < 64 << 20


def test_a_vendored_xz_above_the_compressed_cap_is_refused_unread(planted, monkeypatch):
    monkeypatch.setattr(real_maps, "MAX_PACKED_BYTES", 32)
    path = planted.folder / (planted.originals[1] + ".xz")
    assert f"{path}: " in refusal(real_maps.original_bytes, planted.name, planted.originals[1])


@pytest.mark.parametrize("body, line", [
    ("abc\n", 1),
    (f"{'0' * 64}  yujin-rnd/a.yaml\n\nnot a line\n", 3),
    (f"{'0' * 64} yujin-rnd/a.yaml\n", 1),
    (f"{'g' * 64}  yujin-rnd/a.yaml\n", 1),
    (f"{'0' * 64}  a.yaml\n", 1),
])
def test_a_malformed_manifest_is_one_line_naming_the_file_and_the_line(planted, body, line):
    real_maps.MANIFEST.write_text(body)
    assert f"{real_maps.MANIFEST}: line {line} is not" in refusal(real_maps.manifest)


def test_a_manifest_above_its_cap_or_not_text_is_refused_in_one_line(planted):
    real_maps.MANIFEST.write_text(f"{'0' * 64}  yujin-rnd/a.yaml\n" * 4000)  # 332 KB
    assert "above" in refusal(real_maps.manifest)
    real_maps.MANIFEST.write_bytes(b"\xff\xfe  yujin-rnd/a.yaml\n")
    assert f"{real_maps.MANIFEST}: not UTF-8" in refusal(real_maps.manifest)


def test_the_cli_says_a_broken_vendored_map_in_one_line_with_exit_2(planted, tmp_path, capsys):
    path = planted.folder / (planted.originals[1] + ".xz")
    path.write_bytes(path.read_bytes()[:40])
    assert main(["worlds", "show", "real:yujin-rnd", "--out", str(tmp_path / "w.png")]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert lines == [f"curlnav: error: {path}: not a whole xz file (it ends early); refused"]
