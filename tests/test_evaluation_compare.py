"""``curlnav eval`` comparing agents side by side (the classical planner and policies), its
metrics, and the unseen NAMO worlds they are compared on."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from curlnav.cli import main
from curlnav.evaluation.compare import Episode, summarise
from curlnav.layout import ObservationLayout
from curlnav.sim import EnvConfig
from curlnav.worlds.difficulty.rank import path_points, world_paths
from curlnav.worlds.families import FAMILIES, generate
from curlnav.worlds.procedural.namo import NAMO_FAMILIES, door_crossings

T_MAZE = Path(__file__).resolve().parent.parent / "scheduler" / "curricula" / "worlds" / "t-maze-0.yaml"
PLANNER = "oracle"  # `planner` is the old name of the oracle, still accepted


@pytest.fixture(scope="module")
def untrained_policy(tmp_path_factory) -> Path:
    from curlnav.config import D4PGConfig
    from curlnav.learner.artefact import export_policy
    from curlnav.learner.d4pg import init_state

    state = init_state(D4PGConfig(seed=1), ObservationLayout.from_env_config(EnvConfig()), "cpu")
    return export_policy(state, tmp_path_factory.mktemp("artefact") / "policy", EnvConfig(), worlds=["open-room"])


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.slow  # more than 5 s
def test_eval_puts_the_planner_and_a_policy_side_by_side_on_the_same_pairs_and_seeds(tmp_path, capsys,
                                                                                      untrained_policy):
    out = tmp_path / "results"
    policy = str(untrained_policy)
    assert main(["eval", "planner", policy, "--world", "namo-office:0", "--world", "open-room", "--pairs", "1",
                 "--seeds", "2", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    header = next(line for line in printed.splitlines() if line.startswith("world"))
    assert PLANNER in header and policy in header
    for block in ("namo-office-0 (2 episodes)", "open-room (2 episodes)", "all (4 episodes)"):
        assert block in printed
    for metric in ("success", "base collisions/trial", "arm collisions/trial", "time to goal (s)", "path length (m)",
                   "SPL"):
        assert f" {metric} " in printed

    episodes = read_csv(out / "episodes.csv")
    assert len(episodes) == 2 * 2 * 1 * 2  # agents x worlds x pairs x seeds
    runs: dict[tuple[str, str], list] = {}
    for e in episodes:
        runs.setdefault((e["agent"], e["world"]), []).append((e["pair"], e["seed"]))
    for world in ("namo-office-0", "open-room"):
        assert runs[(PLANNER, world)] == runs[(policy, world)]  # same pairs and seeds for every agent
        assert len({seed for _, seed in runs[(PLANNER, world)]}) == 2
    for e in episodes:
        assert 0.0 <= float(e["spl"]) <= 1.0 and float(e["shortest_path_m"]) > 3.0
        if e["success"] == "True":
            assert float(e["spl"]) > 0 and float(e["path_length_m"]) >= 0.9 * float(e["shortest_path_m"])
    planner_wins = [e["success"] == "True" for e in episodes if e["agent"] == PLANNER]
    assert all(planner_wins), episodes

    summary = read_csv(out / "summary.csv")
    assert {(s["agent"], s["world"]) for s in summary} == {(a, w) for a in (PLANNER, policy)
                                                           for w in ("namo-office-0", "open-room", "all")}
    pictures = sorted(p.name for p in (out / "trajectories").glob("*.png"))
    assert pictures == ["namo-office-0-p1.png", "open-room-eval-0.png"]


def test_the_one_policy_form_of_eval_still_works(capsys, untrained_policy):
    assert main(["eval", str(untrained_policy), "--world", str(T_MAZE), "--pair", "p4", "--episodes", "2"]) == 0
    out = capsys.readouterr().out.splitlines()
    trials, lines = [line for line in out if line.startswith("trial ")], [line for line in out if not line.startswith("trial ")]
    assert len(trials) == 2  # a line per trial as it finishes, then the summary
    assert len(lines) == 1 and lines[0].startswith(f"{untrained_policy} on t-maze-0: ")
    assert "over 2 episodes" in lines[0]


def test_spl_weights_each_success_by_how_close_its_path_came_to_the_shortest():
    def episode(success: bool, driven: float, shortest: float = 10.0, time_s: float = 20.0) -> Episode:
        spl = shortest / max(driven, shortest) if success else 0.0
        return Episode("a", "w", "p", 0.0, 0.0, 1.0, 1.0, 0, success, time_s, 2, 1, driven, shortest, spl)

    (per_world, overall) = summarise([episode(True, 10.0), episode(True, 20.0, time_s=40.0), episode(False, 5.0),
                                      episode(False, 30.0)])
    assert per_world.world == "w" and overall.world == "all"
    assert per_world.success_rate == 0.5
    assert per_world.spl == pytest.approx((1.0 + 0.5) / 4)
    assert per_world.time_to_goal_s == pytest.approx(30.0)  # over successful trials only
    assert per_world.path_length_m == pytest.approx(15.0)
    assert per_world.base_collisions_per_trial == 2 and per_world.arm_collisions_per_trial == 1


# -- unseen NAMO worlds --------------------------------------------------------------------------------
@pytest.mark.parametrize("family", sorted(NAMO_FAMILIES))
def test_a_namo_world_is_made_from_its_seed_with_every_pair_through_a_door_it_can_push_open(family):
    world = generate(family, 0)
    again = FAMILIES[family](seed=0)
    assert np.array_equal(world.occupancy, again.occupancy)
    assert (world.doors, world.balls, world.pairs) == (again.doors, again.balls, again.pairs)
    assert not np.array_equal(generate(family, 1).occupancy, world.occupancy)
    assert len(world.pairs) >= 10 and len(world.balls) >= 5 and world.doors
    assert 15.0 <= max(world.size) <= 30.0

    _, paths = world_paths(world)  # every pair connected on the static grid (MetricsError otherwise)
    for pair, path in zip(world.pairs, paths):
        points = np.stack(path_points(world, path), axis=1)
        crossings = door_crossings(world, points)
        assert crossings, f"{pair.name}: its shortest path crosses no door"
        assert all(forward for _, forward in crossings), f"{pair.name}: a door on its path opens against it"


def test_the_shipped_namo_policy_gets_through_t_maze_p4_with_the_turn(capsys):
    """``policies/namo-s1s2`` is what a user tries first: it loads, and the greedy policy reaches the
    goal of T-Maze p4 (stem room, through the doors and the gate, a turn) in at least 3 of 4 episodes
    with the balls re-placed, and touches walls at most 0.5 times per trial, the issue's bar (the
    evaluation is seeded, so this is the same 4 episodes every time)."""
    shipped = Path(__file__).resolve().parent.parent / "policies" / "namo-s1s2"
    assert main(["eval", str(shipped), "--world", str(T_MAZE), "--pair", "p4", "--episodes", "4"]) == 0
    line = capsys.readouterr().out.splitlines()[-1]
    success = int(line.split("success ")[1].split("%")[0])
    events = float(line.split("(")[1].split(" contact events")[0])
    assert success >= 75 and events <= 0.5, line


def test_an_agent_scores_the_same_whatever_its_place_in_the_eval_list():
    """Two agents with the same weights must drive the same trajectories: an agent's result may not
    depend on which agents ran before it (PyBullet keeps solver warm-start state across resets, so
    a shared environment made the second copy drift; measured once: 93 % against 90 %)."""
    from curlnav.config import ExperimentConfig
    from curlnav.evaluation.compare import Comparison, episode_pairs
    from curlnav.learner.artefact import load_policy
    from curlnav.nav import make_agent
    from curlnav.sim import get_world

    env_config = ExperimentConfig().eval_env
    shipped = Path(__file__).resolve().parent.parent / "policies" / "namo-s1-barn"
    _, policy = make_agent(str(shipped), env_config, load_policy)
    world = get_world(str(T_MAZE))
    episodes = Comparison({"first": policy, "second": policy}, [world],
                          lambda w: episode_pairs(w, ["p4"], None, 1), env_config).run()
    first, second = [e for e in episodes if e.agent == "first"], [e for e in episodes if e.agent == "second"]
    assert len(first) == len(second) == 1
    assert first[0].trajectory == second[0].trajectory, "the second copy of the same policy drove another path"


@pytest.mark.slow  # more than 5 s
@pytest.mark.parametrize("senses", ["none", "realistic-frame"])
def test_the_flagship_as_shipped_drives_namo_worlds_it_never_saw(capsys, senses):
    """``policies/namo-robust`` is the README's flagship, named alone: behind the rescue (with its
    own settings), the shield and the laser odometry its metadata ships, on the three NAMO floors
    of a held-out seed (300, never trained or tuned on) it reaches the goal without touching a
    wall, with exact senses and with a robot's (``realistic-frame``: noisy ranges and labels,
    latency, drifting odometry, every error lasting one frame, the senses its published figures were
    measured with; seeded evaluation: the same 12 trials every time; the full figures, real
    maps included, are in its README; the real maps are not in the repository, so no test drives
    them)."""
    shipped = Path(__file__).resolve().parent.parent / "policies" / "namo-robust"
    assert main(["eval", str(shipped), "--world", "namo-office:300", "--world", "namo-indoor:300",
                 "--world", "namo-auditorium:300", "--pairs", "2", "--seeds", "2", "--sensor-noise", senses]) == 0
    out = capsys.readouterr().out
    assert "driven as its artefact ships it" in out and "+scan-match" in out \
        and "its rescue: stall_steps 10, max_steps 50" in out, out[-2000:]
    line = next(x for x in out.splitlines() if " on all: " in x)
    success = int(line.split("success ")[1].split("%")[0])
    events = float(line.split("(")[1].split(" contact events")[0])
    # here: 100 % and 92 %, no contact; the network alone 67 % and 75 %
    assert success >= 80 and events <= 0.1, line


def test_the_clean_senses_policy_drives_namo_worlds_it_never_saw(capsys):
    """``policies/namo-general`` (the flagship before ``namo-robust``; the network alone): on NAMO
    floors of a held-out seed (300, never trained or tuned on) it reaches the goal pushing balls
    and doors, with few wall contacts (seeded evaluation: the same 8 trials every time; the full
    60-trial figure is in its README)."""
    shipped = Path(__file__).resolve().parent.parent / "policies" / "namo-general"
    assert main(["eval", str(shipped), "--world", "namo-office:300", "--world", "namo-indoor:300",
                 "--pairs", "2", "--seeds", "2"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if " on all: " in x)
    success = int(line.split("success ")[1].split("%")[0])
    events = float(line.split("(")[1].split(" contact events")[0])
    assert success >= 75 and events <= 0.5, line
