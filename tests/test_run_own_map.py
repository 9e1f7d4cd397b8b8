"""A user's own SLAM map as a training target: ``curlnav train --world MAP.yaml`` draws training and
held-out pairs apart into the run's pairs.yaml (fixed by the seed, read back on a resume), the
evaluation scores the held-out ones, doors and balls go where asked, and a bad map is refused in
one line with exit 2 and nothing in the run folder. No training runs here: the trainers are
replaced by a stub that records the experiment they were given."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

import curlnav.run.train as train
from curlnav.cli import main

FREE, WALL = 254, 0


def write_map(folder, name: str = "building", pixels: np.ndarray | None = None, resolution: float = 0.1,
              cut: int | None = None, header: bytes | None = None, image: str | None = None):
    """A map_server map ``name.yaml`` + ``name.pgm`` written by hand (top row first, as map_server
    stores it); by default a 12 m x 8 m room, walled, with a wall half across it. ``cut``: keep only
    that many bytes of the PGM; ``header``: the PGM's header instead of the one its pixels call for."""
    if pixels is None:
        pixels = np.full((80, 120), FREE, dtype=np.uint8)
        pixels[:2], pixels[-2:], pixels[:, :2], pixels[:, -2:] = WALL, WALL, WALL, WALL
        pixels[:50, 60:62] = WALL
    rows, cols = pixels.shape
    data = (header or f"P5\n# CREATOR: map_saver {resolution:.3f} m/pix\n{cols} {rows}\n255\n".encode())
    data += pixels.astype(np.uint8).tobytes()
    (folder / f"{name}.pgm").write_bytes(data[:cut] if cut is not None else data)
    path = folder / f"{name}.yaml"
    path.write_text(f"image: {image or name + '.pgm'}\nresolution: {resolution}\norigin: [-3.0, 1.5, 0.0]\n"
                    f"negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n")
    return path


@pytest.fixture
def trained(monkeypatch):
    """Stub trainers: each call appends (mode, run folder, experiment) and returns 0."""
    calls = []
    monkeypatch.setattr(train, "_train_serial", lambda args, run_dir, experiment: calls.append(
        ("serial", run_dir, experiment)) or 0)
    monkeypatch.setattr(train, "_train_distributed", lambda args, run_dir, experiment, actors: calls.append(
        ("distributed", run_dir, experiment)) or 0)
    return calls


def pairs_of(run):
    return yaml.safe_load((run / "pairs.yaml").read_text())


def test_train_on_a_map_writes_disjoint_training_and_held_out_pairs_fixed_by_the_seed(tmp_path, trained, capsys):
    building = write_map(tmp_path)
    runs = [tmp_path / "serial", tmp_path / "distributed", tmp_path / "seed-1"]
    assert main(["train", "--serial", "--world", str(building), "--run-dir", str(runs[0]), "--pairs-train", "40"]) == 0
    assert main(["train", "--world", str(building), "--run-dir", str(runs[1]), "--pairs-train", "40"]) == 0
    assert main(["train", "--serial", "--world", str(building), "--run-dir", str(runs[2]), "--pairs-train", "40",
                 "--seed", "1"]) == 0
    assert "40 training and 20 held-out start/goal pairs (seed 0)" in capsys.readouterr().out
    # same map and seed: the same file, in either mode; another seed: other pairs
    assert (runs[0] / "pairs.yaml").read_bytes() == (runs[1] / "pairs.yaml").read_bytes()
    assert pairs_of(runs[2])["held_out"] != pairs_of(runs[0])["held_out"]
    pairs = pairs_of(runs[0])
    assert pairs["map"] == str(building.resolve()) and pairs["seed"] == 0
    assert (len(pairs["train"]), len(pairs["held_out"])) == (40, 20)
    for pair in pairs["train"] + pairs["held_out"]:
        assert set(pair) == {"name", "start", "goal"} and len(pair["start"]) == 3 and len(pair["goal"]) == 2
        assert all(isinstance(v, float) for v in pair["start"] + pair["goal"])
    def key(p):
        return tuple(p["start"][:2] + p["goal"])

    def reverse(p):
        return tuple(p["goal"] + p["start"][:2])

    train_keys = {key(p) for p in pairs["train"]} | {reverse(p) for p in pairs["train"]}
    assert not train_keys & {key(p) for p in pairs["held_out"]}, "a held-out pair is a training pair"
    assert len({p["name"] for p in pairs["train"] + pairs["held_out"]}) == 60
    # the run trains on its task world, whose own pairs are the training pairs; each evaluation
    # scores every held-out pair once
    mode, run, experiment = trained[0]
    assert experiment.curriculum.world == str(run / "world" / "building.yaml")
    assert experiment.evaluation.episodes == 20
    assert str(run / "world" / "building.yaml") in (run / "config.yaml").read_text()


def test_the_evaluation_scores_the_held_out_pairs_and_training_draws_only_training_ones(tmp_path, trained):
    from curlnav.builder import D4PGBuilder
    from curlnav.evaluation.compare import episode_pairs
    from curlnav.evaluation.protocol import EvaluationProtocol
    from curlnav.sim import get_world

    run = tmp_path / "run"
    assert main(["train", "--serial", "--world", str(write_map(tmp_path)), "--run-dir", str(run),
                 "--pairs-held-out", "5", "--pairs-train", "8"]) == 0
    experiment = trained[0][2]
    pairs = pairs_of(run)
    protocol = EvaluationProtocol(experiment)  # the serial trainer's and the evaluator's
    assert [(p.name, [p.x, p.y, p.yaw], [p.gx, p.gy]) for p in protocol.pairs] == \
        [(p["name"], p["start"], p["goal"]) for p in pairs["held_out"]]
    # curlnav eval on the run's task world: the same pairs, each once
    assert episode_pairs(get_world(experiment.curriculum.world)) == protocol.pairs
    env = D4PGBuilder(experiment).make_env()  # every actor's training environment
    try:
        drawn = set()
        for seed in range(12):
            env.reset(seed=seed)
            drawn.add(env.pair.name)
    finally:
        env.close()
    assert drawn <= {p["name"] for p in pairs["train"]} and len(drawn) > 3


def test_a_resumed_run_reads_its_pairs_back_and_never_draws_new_ones(tmp_path, trained, monkeypatch, capsys):
    from curlnav.worlds.real import own_map

    building = write_map(tmp_path)
    run = tmp_path / "run"
    assert main(["train", "--serial", "--world", str(building), "--run-dir", str(run), "--pairs-train", "10"]) == 0
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "latest.safetensors").write_bytes(b"")  # a run to resume
    written = (run / "pairs.yaml").read_bytes()
    monkeypatch.setattr(own_map, "draw_task", lambda *a, **k: pytest.fail("a resume drew new pairs"))
    # with its saved config, or naming the map again with the same options
    assert main(["train", "--serial", "--run-dir", str(run), "--resume"]) == 0
    assert main(["train", "--serial", "--run-dir", str(run), "--resume", "--world", str(building),
                 "--pairs-train", "10"]) == 0
    assert (run / "pairs.yaml").read_bytes() == written
    assert trained[1][2].curriculum.world == trained[2][2].curriculum.world == trained[0][2].curriculum.world
    # pairs.yaml edited by hand: the run's task world follows it
    pairs = pairs_of(run)
    pairs["held_out"] = pairs["held_out"][:3]
    (run / "pairs.yaml").write_text(yaml.safe_dump(pairs))
    capsys.readouterr()
    assert main(["train", "--serial", "--run-dir", str(run), "--resume"]) == 0
    assert "10 training and 3 held-out pairs read back from" in capsys.readouterr().out
    from curlnav.sim import get_world

    assert [p.name for p in get_world(trained[-1][2].curriculum.world).held_out] == ["h1", "h2", "h3"]
    # other options on a resume: refused, nothing changed
    capsys.readouterr()
    assert main(["train", "--serial", "--run-dir", str(run), "--resume", "--balls", "2"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--resume keeps the run's pairs" in err and "leave out --balls" in err


def test_doors_from_a_file_and_balls_on_the_training_paths(tmp_path, trained, capsys):
    from curlnav.sim import NamoEnv, get_world
    from curlnav.worlds.real import own_map

    building = write_map(tmp_path)
    doors = tmp_path / "doors.yaml"
    # the gap under the half wall, x 3.0..3.2: a door hinged at its foot, closed across the room's lower half
    doors.write_text("doors:\n  - {hinge: [3.1, 1.7], width: 1.2, angle: 1.5708, swing: right}\n")
    run = tmp_path / "run"
    assert main(["train", "--serial", "--world", str(building), "--run-dir", str(run), "--pairs-train", "20",
                 "--doors", str(doors), "--balls", "3"]) == 0
    task = get_world(trained[0][2].curriculum.world)
    assert len(task.doors) == 1 and task.doors[0].swing == "right" and task.doors[0].width == 1.2
    assert len(task.balls) == 3
    for ball in task.balls:
        for pair in task.pairs + task.held_out:
            assert np.hypot(ball.x - pair.x, ball.y - pair.y) > 1.0, "a ball at a start"
    assert pairs_of(run)["doors"] == str(doors.resolve()) and pairs_of(run)["balls"] == 3
    # every reset re-places each ball near where it was drawn, and the evaluation meets two placements a pair
    assert trained[0][2].evaluation.episodes == own_map.PLACEMENTS_PER_PAIR * len(task.held_out)
    env = NamoEnv(task)
    try:
        placements = []
        for seed in (1, 2):
            env.reset(seed=seed, options={"pair": task.held_out[0]})
            placements.append(np.array(env.scene.ball_positions()))
    finally:
        env.close()
    drawn = np.array([[b.x, b.y] for b in task.balls])
    assert np.all(np.abs(placements[0] - drawn) <= own_map.BALL_SPREAD_M + 1e-6)
    assert np.all(np.abs(placements[1] - drawn) <= own_map.BALL_SPREAD_M + 1e-6)
    assert np.abs(placements[0] - placements[1]).max() > 0.1, "two resets left the balls where they were"
    # a door drawn into a wall: refused, naming the door
    doors.write_text("- {hinge: [3.1, 6.0], width: 1.0, angle: 1.5708}\n")
    assert main(["train", "--serial", "--world", str(building), "--run-dir", str(tmp_path / "wall"), "--doors",
                 str(doors)]) == 2
    err = capsys.readouterr().err
    assert "doors[0]: the closed panel" in err and not (tmp_path / "wall").exists()


def _closed(tmp_path):
    pixels = np.full((40, 40), WALL, dtype=np.uint8)
    pixels[18:22, 18:22] = FREE  # 0.4 m square: no room for the robot
    return write_map(tmp_path, "closed", pixels)


def _few_pairs(tmp_path):
    pixels = np.full((8, 8), WALL, dtype=np.uint8)
    pixels[2:6, 1:7] = FREE  # 3 m x 2 m at 0.5 m a cell: a dozen pairs at most
    return write_map(tmp_path, "small", pixels, resolution=0.5)


BAD_MAPS = {
    "no room for the robot": (_closed, "no connected free space for a start/goal pair"),
    "a truncated PGM": (lambda tmp: write_map(tmp, cut=3000), "is truncated: its header says 120 x 80 pixels"),
    "100 million cells": (lambda tmp: write_map(tmp, pixels=np.full((4, 4), FREE), header=b"P5\n10000 10000\n255\n"),
                          "10000 x 10000 = 100000000 cells, above the cap of 25000000"),
    "too few pairs": (_few_pairs, "found only"),
    "an image that is not there": (lambda tmp: write_map(tmp, image="scan.pgm"), "scan.pgm does not exist"),
}


@pytest.mark.parametrize("bad", BAD_MAPS, ids=list(BAD_MAPS))
def test_a_bad_map_is_refused_in_one_line_with_nothing_in_the_run_folder(tmp_path, trained, capsys, bad):
    make, message = BAD_MAPS[bad]
    world = make(tmp_path)
    for mode in (["--serial"], []):
        run = tmp_path / "run"
        assert main(["train", *mode, "--world", str(world), "--run-dir", str(run)]) == 2
        err = capsys.readouterr().err
        assert err.startswith("curlnav: error: ") and err.count("\n") == 1 and message in err, err
        assert not run.exists() and not trained
    # eval reads maps with the same loader
    if bad != "too few pairs":
        assert main(["eval", "planner", "--world", str(world), "--pairs", "1", "--out", str(tmp_path / "eval")]) == 2
        assert message in capsys.readouterr().err and not (tmp_path / "eval").exists()


@pytest.mark.parametrize("option, value, message", [
    ("--pairs-held-out", "0", "--pairs-held-out must be 1..1000, got 0"),
    ("--pairs-train", "1001", "--pairs-train must be 1..1000, got 1001"),
    ("--balls", "-1", "--balls must be 0..200, got -1"),
    ("--pairs-held-out", "many", "argument --pairs-held-out: invalid int value"),
])
def test_the_map_options_are_validated(tmp_path, trained, capsys, option, value, message):
    run = tmp_path / "run"
    try:
        code = main(["train", "--serial", "--world", str(write_map(tmp_path)), "--run-dir", str(run), option, value])
    except SystemExit as exc:  # argparse's own refusal of a value that is no number
        code = exc.code
    assert code == 2 and message in capsys.readouterr().err and not run.exists()


def test_the_map_options_are_refused_on_a_world_with_pairs_of_its_own(tmp_path, trained, capsys):
    assert main(["train", "--serial", "--world", "t-maze:0", "--run-dir", str(tmp_path / "run"), "--balls", "2"]) == 2
    assert "t-maze:0 is not a map file" in capsys.readouterr().err



def test_a_generated_world_exported_as_a_map_is_what_a_slam_map_is(tmp_path, capsys):
    """``curlnav worlds export-map``: the walls alone, in map_server's fields, read back cell for cell."""
    from curlnav.sim import get_world

    out = tmp_path / "maps" / "office.yaml"
    assert main(["worlds", "export-map", "namo-office:97", "--out", str(out)]) == 0
    assert list(yaml.safe_load(out.read_text())) == ["image", "resolution", "origin", "mode", "negate",
                                                     "occupied_thresh", "free_thresh"]
    original, exported = get_world("namo-office:97"), get_world(str(out))
    assert np.array_equal(original.occupancy, exported.occupancy)
    assert exported.resolution == original.resolution and exported.origin == original.origin
    assert not (exported.pairs or exported.balls or exported.doors or exported.boxes)
    # its doors, as a team would mark them: a doors file that train --doors reads back to the same doors
    from curlnav.worlds.real.own_map import read_doors

    doors = tmp_path / "maps" / "office-doors.yaml"
    assert main(["worlds", "export-map", "namo-office:97", "--out", str(out), "--doors-out", str(doors)]) == 0
    marked = read_doors(doors, exported)
    assert len(marked) == len(original.doors) >= 1
    for a, b in zip(marked, original.doors):
        assert a.swing == b.swing and np.allclose([a.hinge_x, a.hinge_y, a.width, a.closed_angle, a.max_open, a.mass,
                                                   a.hinge_friction],
                                                  [b.hinge_x, b.hinge_y, b.width, b.closed_angle, b.max_open, b.mass,
                                                   b.hinge_friction], atol=1e-4)
    assert main(["worlds", "export-map", "open-room", "--out", str(out), "--doors-out", str(doors)]) == 2
    assert "open-room has no doors" in capsys.readouterr().err
