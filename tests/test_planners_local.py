"""The baselines of Table II: the map-less local planners (``tare-l``, ``dwa``) see only what the
policy sees, a trap deeper than their range defeats them and not the ``oracle`` (A* on the true
map), the oracle does not freeze beside a wall, and a policy behind a global plan crosses a
building it cannot cross alone."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from conftest import u_trap_world, walled_room

from curlnav.evaluation.protocol import evaluate, evaluation_config, held_out_pairs
from curlnav.nav.controllers.local import DynamicWindowPlanner, TareLocalPlanner
from curlnav.nav.global_planners.global_plan import GlobalPlanAgent
from curlnav.nav.global_planners.oracle import GridPlanner, StaticMapPlanner
from curlnav.sim import NamoEnv, StartGoal, World
from curlnav.worlds.core.pairs import clearance_map

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("make", [TareLocalPlanner, DynamicWindowPlanner], ids=["tare-l", "dwa"])
def test_the_map_less_planners_act_the_same_when_the_static_map_is_emptied(make):
    """They get the world at reset (the protocol's interface) but must not use it: fed the same
    scans, goals and odometry, an agent told of an empty world acts exactly as one told the truth."""
    cfg = evaluation_config()
    env = NamoEnv("namo-office:300", cfg)
    world = env.world
    empty = world.with_changes(occupancy=np.zeros_like(world.occupancy), doors=(), balls=())
    pair = held_out_pairs(world, 1)[0]
    seeing, blind = make(cfg), make(cfg)
    try:
        obs, info = env.reset(seed=3, options={"pair": pair})
        seeing.reset(world, env.pair)
        blind.reset(empty, env.pair)
        for _ in range(80):
            action = seeing.act(obs, info)
            assert np.array_equal(action, blind.act(obs, info))
            obs, _, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                break
        assert info["steps"] >= 20  # it did drive
    finally:
        env.close()


def test_a_u_shaped_trap_defeats_the_map_less_planners_and_the_oracle_gets_round_it():
    cfg = evaluation_config()
    world = u_trap_world()
    outcomes = {}
    for agent in (TareLocalPlanner(cfg), DynamicWindowPlanner(cfg), StaticMapPlanner(cfg)):
        outcomes[agent.label] = evaluate(agent, world, list(world.pairs), cfg).success_rate
    assert outcomes == {"tare-l": 0.0, "dwa": 0.0, "oracle": 1.0}


def test_the_oracle_turns_in_place_when_a_wall_blocks_every_arc_instead_of_freezing():
    """A wall 0.55 m ahead across the front beams and the path straight through it: the
    pursuit arc's speed is capped to 0, and so was the turn (``w = v * curvature``)."""
    cfg = evaluation_config()
    grid = walled_room(12.0, 8.0)
    pair = StartGoal("p", 6.0, 4.0, 0.0, 10.0, 4.0)
    world = World(name="room", occupancy=grid, resolution=0.1, pairs=(pair,))
    oracle = StaticMapPlanner(cfg)
    oracle.reset(world, pair)
    layout = oracle.layout
    angles = np.linspace(-cfg.lidar_fov / 2, cfg.lidar_fov / 2, cfg.lidar_beams)
    ranges = np.full(cfg.lidar_beams, cfg.lidar_max_range, dtype=np.float32)
    ahead = np.abs(angles) < math.radians(75)
    ranges[ahead] = np.minimum(0.55 / np.cos(angles[ahead]), cfg.lidar_max_range)
    obs = np.zeros(layout.size, dtype=np.float32)
    obs[:layout.range_frames * layout.beams] = np.tile(ranges, layout.range_frames)
    action = oracle.act(obs, {"pose": (pair.x, pair.y, pair.yaw)})
    assert action[0] == 0.0 and abs(action[1]) >= 0.5


@pytest.mark.parametrize("yaw_deg", [0, 45, 90, 135])
def test_the_oracle_started_061_m_from_a_wall_reaches_its_goal(yaw_deg):
    """The Husky's half-diagonal is 0.60 m: from 0.61 m it can turn, and must."""
    cfg = evaluation_config()
    grid = walled_room(12.0, 8.0)
    wall = 8.0 - 0.2  # the top wall's face
    pair = StartGoal("p", 6.0, wall - 0.61, math.radians(yaw_deg), 9.0, 2.0)
    world = World(name="room", occupancy=grid, resolution=0.1, pairs=(pair,))
    result = evaluate(StaticMapPlanner(cfg), world, [pair], cfg)
    assert result.success_rate == 1.0 and result.mean_time_to_goal_s < 20.0, result.line()


def far_pair(world: World, half_width: float, low: float, high: float, seed: int = 0) -> StartGoal:
    """A start and goal whose shortest path on the static grid is ``low``-``high`` m long."""
    planner = GridPlanner(world, half_width)
    clearance = clearance_map(world)  # m from each cell to the nearest wall
    free = np.argwhere(clearance >= 0.8)
    rng = np.random.default_rng(seed)
    for _ in range(200):
        (ay, ax), (by, bx) = free[rng.integers(len(free), size=2)]
        (x0, y0), (x1, y1) = world.cell_centre(int(ay), int(ax)), world.cell_centre(int(by), int(bx))
        if 0.75 * low <= math.hypot(x1 - x0, y1 - y0) <= 0.8 * high \
                and low <= planner.shortest_length((x0, y0), (x1, y1)) <= high:
            return StartGoal("far", x0, y0, float(rng.uniform(-math.pi, math.pi)), x1, y1)
    raise AssertionError("no pair that far apart")


@pytest.mark.benchmark  # minutes: A* searches on a 1840 x 1440 grid to find the pair, two 60 s episodes
@pytest.mark.xfail(reason="namo-s1-barn behind the plan still gets pinned in cluttered doorways of slam-office "
                          "(2 of 2 pairs tried, 2026-11-25); the 10-20 m pairs of the unseen suite mostly pass",
                   strict=False)
def test_on_slam_office_a_policy_behind_a_global_plan_crosses_rooms_it_cannot_cross_alone():
    from curlnav.policy import PolicyArtefact
    from curlnav.worlds.families import generate

    cfg = evaluation_config()
    world = generate("slam-office", 300)
    pair = far_pair(world, cfg.robot.base_width / 2, 30.0, 40.0)
    policy = PolicyArtefact(ROOT / "policies" / "namo-s1-barn")
    env = NamoEnv(world, cfg)
    try:
        alone = evaluate(policy, world, [pair], cfg, env=env)
        planned = evaluate(GlobalPlanAgent(policy, cfg), world, [pair], cfg, env=env)
    finally:
        env.close()
    assert alone.success_rate == 0.0, alone.line()
    assert planned.success_rate == 1.0, planned.line()


def test_the_unseen_suite_prints_table_ii_and_writes_it_with_the_csv_files(tmp_path, capsys, monkeypatch):
    """The suite's layout: a row per world and one over all, a column per agent, success with
    its 95 % interval; the worlds and trials are the suite's (a tiny one here): a world that
    re-places its balls runs a pair once per placement, one whose balls stay put distinct pairs."""
    from curlnav.cli import main
    from curlnav.evaluation import compare

    tiny = compare.Suite("unseen", ("open-room", "namo-office:300"), trials=2, ball_placements=2, about="tiny")
    monkeypatch.setitem(compare.SUITES, "unseen", tiny)
    assert main(["eval", "tare-l", "--suite", "unseen", "--world", "open-room"]) != 0
    assert "drop --world" in capsys.readouterr().err
    out = tmp_path / "suite"
    assert main(["eval", "tare-l", "oracle", "--suite", "unseen", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| world | tare-l | oracle |" in printed
    for row in ("| open-room (2) |", "| namo-office-300 (2) |", "| **all** (4) |"):
        assert row in printed
    oracle_all = next(line for line in printed.splitlines() if line.startswith("| **all**")).split("|")[3]
    assert oracle_all.strip().startswith("100% (51%-100%) · 0.00 ·")  # 4 of 4: Wilson's interval
    assert (out / "table2.md").read_text().count("| **all** (4) |") == 1
    import csv

    with open(out / "episodes.csv", newline="") as f:
        trials = [(r["world"], r["pair"], r["seed"]) for r in csv.DictReader(f) if r["agent"] == "oracle"]
    room = [t for t in trials if t[0] == "open-room"]
    assert len({p for _, p, _ in room}) == 1 and len({s for _, _, s in room}) == 2  # one pair, two placements
    assert len({p for w, p, _ in trials if w == "namo-office-300"}) == 2  # fixed balls: two pairs
    assert len(list((out / "trajectories").glob("*.png"))) == 3


def test_the_wilson_interval_matches_its_textbook_values():
    from curlnav.evaluation.compare import wilson_interval

    assert wilson_interval(8, 10) == pytest.approx((0.4902, 0.9433), abs=1e-4)
    assert wilson_interval(0, 20)[0] == 0.0 and wilson_interval(0, 20)[1] == pytest.approx(0.1611, abs=1e-4)
