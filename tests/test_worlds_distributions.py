"""World distributions as curriculum material (issue 28): a stage names a generator family with
seed and parameter ranges; both training modes draw a world per episode (or every K), keep the
scenes of recent worlds built, and never draw a held-out seed."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import episode_loop, one_episode

from curlnav.config import CurriculumConfig, ExperimentConfig
from curlnav.scheduler.curriculum import CurriculumError, check_curriculum, load_curriculum
from curlnav.sim import NamoEnv, get_world
from curlnav.worlds.core.heldout import HELD_OUT_FROM, HeldOutSeedError, held_out_seeds, training_seeds
from curlnav.worlds.distribution import DistributionError, WorldDistribution, WorldDraws

BARN = "{family: barn-3x3, seeds: [0, 99], params: {fill_pct: [0.10, 0.30], smooth_iter: [3, 4]}, every: 4}"
TINY = "t-maze:0-9(every=2,pool=2)"  # t-maze worlds build in milliseconds


def _curriculum(tmp_path, worlds: str, extra: str = ""):
    path = tmp_path / "c.yaml"
    path.write_text(f"name: d\nstages:\n  - name: S1\n    worlds: {worlds}\n{extra}")
    return load_curriculum(path)


def test_a_stage_names_a_distribution_next_to_world_files_and_it_loads_as_one_canonical_key(tmp_path):
    c = _curriculum(tmp_path, f"[{BARN}, open-room, 't-maze:0-9']")
    key = c.stages[0].worlds[0]
    assert key == "barn-3x3:0-99(fill_pct=0.1~0.3,smooth_iter=3~4,every=4)"
    assert c.stages[0].worlds[1:] == ("open-room", "t-maze:0-9")
    assert WorldDistribution.parse(key).key == key, "the key is what actors parse: it round-trips"
    dist = WorldDistribution.parse(key)
    assert dist.params_of(7) == dist.params_of(7) and 0.1 <= dist.params_of(7)["fill_pct"] <= 0.3
    assert {dist.params_of(s)["smooth_iter"] for s in range(20)} == {3, 4}, "integer ranges are inclusive"
    check_curriculum(c)  # a distribution's first world loads (and would be checked for sub-step pairs)
    first = get_world(key)
    assert first.name == "barn-3x3-0" and key in first.source


def test_a_distributions_worlds_are_reproducible_per_seed():
    dist = WorldDistribution.parse("barn-3x3:0-99(fill_pct=0.1~0.3)")
    a, b = dist.world(5), dist.world(5)
    assert np.array_equal(a.occupancy, b.occupancy) and a.pairs == b.pairs
    assert not np.array_equal(a.occupancy, dist.world(6).occupancy)


@pytest.mark.parametrize("entry, message", [
    ("{family: barn-3x3, seeds: [0, 100]}", "reach into the held-out seeds (>= 100"),
    ("{family: barn-3x3, seeds: [50, 10]}", "0 <= lo <= hi"),
    ("{family: barn-3x3, seeds: [0]}", "seeds must be [lo, hi]"),
    ("{family: " + "x" * 300 + ", seeds: [0, 9]}", "unknown world family 'xxxxxxxx"),
    ("{family: barn-3x3, seeds: [0, 9], params: {fill: [0.1, 0.3]}}", "has no parameter 'fill'; it takes"),
    ("{family: barn-3x3, seeds: [0, 9], params: {fill_pct: [0.3, 0.1]}}", "lo <= hi"),
    ("{family: barn-3x3, seeds: [0, 9], every: 0}", "every must be a whole number >= 1"),
    ("{family: barn-3x3, seeds: [0, 9], colour: red}", "unknown keys ['colour']"),
    ("'barn-3x3:0-150'", "held-out seeds"),
    ("'namo-office:300'", "namo-office:300 is a held-out world"),
])
def test_malformed_or_held_out_distributions_are_refused_at_load_in_one_short_line(tmp_path, entry, message):
    with pytest.raises(CurriculumError) as caught:
        _curriculum(tmp_path, f"[{entry}]")
    text = str(caught.value)
    assert message in text and "\n" not in text
    assert "x" * 50 not in text, "user values are truncated"


def test_an_evaluate_target_on_a_held_out_seed_is_refused(tmp_path):
    with pytest.raises(CurriculumError, match="namo-indoor:100 is a held-out world"):
        _curriculum(tmp_path, "[open-room]", "evaluate: [{world: 'namo-indoor:100'}]\n")


def test_held_out_seeds_are_one_documented_range_per_family_and_draws_never_reach_it():
    for family in ("barn-3x3", "t-maze", "namo-office", "namo-indoor", "namo-auditorium"):
        assert training_seeds(family) == range(0, HELD_OUT_FROM) and held_out_seeds(family)[0] == HELD_OUT_FROM == 100
    draws = WorldDraws(seed=3)
    dist = WorldDistribution.parse("t-maze:0-99")
    with pytest.raises(HeldOutSeedError, match="held out"):
        draws.world(dist, 100)  # a draw-time refusal, whatever asked for it
    with pytest.raises(DistributionError):
        WorldDistribution.parse("t-maze:90-120")  # a key forged past the curriculum check
    seeds = {int(draws.resolve("t-maze:0-99").name.rsplit("-", 1)[1]) for _ in range(400)}
    assert max(seeds) < 100 and len(seeds) > 90


def test_a_fresh_world_every_k_episodes_the_rest_spread_over_the_pool():
    draws = WorldDraws(seed=0)
    worlds = [draws.resolve("t-maze:0-99(every=3,pool=2)") for _ in range(30)]
    assert draws.generated <= 10 and len({id(w) for w in worlds}) >= 5
    pool: list = []
    for i, w in enumerate(worlds):
        if i % 3 == 0:
            pool = (pool + [w])[-2:]
        assert any(w is p for p in pool), "between fresh draws, the pool's worlds"
    every_episode = WorldDraws(seed=0)
    assert len({id(every_episode.resolve("t-maze:0-99")) for _ in range(20)}) >= 15
    assert WorldDraws(seed=1).resolve("open-room") == "open-room", "other specs pass through"


def test_same_seed_same_draws():
    a, b = WorldDraws(seed=[4, 1]), WorldDraws(seed=[4, 1])
    assert [a.resolve(TINY).name for _ in range(12)] == [b.resolve(TINY).name for _ in range(12)]


def test_the_episode_loop_draws_a_world_per_episode_and_keeps_the_scenes_of_its_pool_built():
    draws = WorldDraws(seed=0)
    loop = episode_loop("t-maze:0", draws)
    try:
        names = [one_episode(loop, i, TINY) for i in range(12)]
        assert loop.env.scene_cache >= draws.cache > 1
        assert len(set(names)) >= 3 and all(n.startswith("t-maze-") for n in names)
        assert loop.env.scene_builds == draws.generated, "a pooled world switched back to is not rebuilt"
        assert draws.generated <= 7
        # a cached scene runs the same episode as a fresh one: same world, pair and seed, same path
        world = get_world("t-maze:3")
        fresh = NamoEnv(world, loop.env.config)
        try:
            for env in (loop.env, fresh):
                env.reset(seed=11, options={"world": world, "pair": "p1"})
                for _ in range(5):
                    env.step(np.array([1.0, 0.3, 0.5], dtype=np.float32))
            assert np.allclose(loop.env.trajectory, fresh.trajectory)
        finally:
            fresh.close()
    finally:
        loop.close()


def test_both_training_modes_draw_from_an_assigned_distribution(tmp_path):
    from curlnav.actor.service import ActorServiceConfig
    from curlnav.builder import D4PGBuilder
    from curlnav.proto.messages import Assignment, AssignmentRequest, EpisodeReport
    from curlnav.run.serial import SerialRunConfig, SerialTrainer
    from curlnav.scheduler.service import SchedulerCore

    path = tmp_path / "c.yaml"
    path.write_text(f"name: d\nstages:\n  - name: S1\n    worlds: ['{TINY}']\n")
    experiment = ExperimentConfig(env=dataclasses.replace(ExperimentConfig().env, max_episode_steps=3),
                                  curriculum=CurriculumConfig(world="open-room", file=str(path)))
    # distributed: the scheduler assigns the key, the actor draws, the report counts under the key
    scheduler = SchedulerCore(load_curriculum(path))
    scheduler.actor_joined("a0")
    assignment = Assignment.decode(scheduler.assign(AssignmentRequest("a0").encode()))
    assert assignment.world == TINY
    # two environments, each its own episodes
    core = D4PGBuilder(experiment).make_actor_core(ActorServiceConfig(actor_id="a0", envs=2))
    try:
        names = []
        while len(names) < 4:
            for k in core.loop.waiting():
                core.loop.begin(k, len(names) + k, {"world": assignment.world})
                names.append(core.loop.envs[k].world.name)
            core.loop.step()
        assert all(n.startswith("t-maze-") for n in names) and core.loop.worlds.fresh_draws(TINY) == 2
    finally:
        core.loop.close()
    report = EpisodeReport("a0", TINY, "", True, 1.0, 0, 0, 3, 0, assignment.epoch).encode()
    scheduler.report(report, sender="a0")
    assert scheduler.state.per_world == {f"{TINY}/": [1, 1]}
    # serial: the in-process scheduler core assigns, the same loop draws
    trainer = SerialTrainer(tmp_path / "run", experiment, SerialRunConfig(progress=False))
    try:
        trainer._begin()
        seen = set()
        while trainer.counters["episodes"] < 8:
            trainer.act_once()
            seen.add(trainer.loop.env.world.name)
        assert trainer.task[0] == TINY and all(n.startswith("t-maze-") for n in seen) and len(seen) >= 2
        assert trainer.curriculum.per_world[f"{TINY}/"][0] == 8
    finally:
        trainer.loop.close()
        trainer.evaluation.close()


@pytest.mark.benchmark
def test_bench_drawing_worlds_prints_steps_per_second():
    from curlnav.bench.draws import run_draw_bench

    rows = run_draw_bench("barn-3x3:0-99(fill_pct=0.1~0.3)", steps=3000, every=(1, 4))
    assert rows[1].worlds_generated > rows[2].worlds_generated > rows[0].worlds_generated == 0


def test_the_general_curriculum_trains_on_distributions_at_training_seeds_and_validates_below_the_held_out_ones():
    from pathlib import Path

    from curlnav.scheduler.curriculum import CurriculumState

    path = Path(__file__).resolve().parents[1] / "scheduler" / "curricula" / "general.yaml"
    c = load_curriculum(path)
    s1, s2 = c.stages
    assert [WorldDistribution.parse(k).family for k in s1.worlds] == ["barn-3x3"]
    assert [WorldDistribution.parse(k).family for k in s2.worlds] == ["t-maze-doors", "namo-office", "namo-indoor",
                                                                      "namo-auditorium"]
    trained = {s for stage in c.stages for k in stage.worlds for s in WorldDistribution.parse(k).seeds}
    validated = {int(w.rsplit(":", 1)[1]) for w, _ in c.evaluation_targets() if ":" in w}
    assert max(trained) < min(validated) <= max(validated) < HELD_OUT_FROM, "validation seeds: never trained on"
    assert s2.sampler == "learning-progress" and s2.replay_earlier == 0.2
    state = CurriculumState(c)
    state.advance()
    assert {state.assign()[0] for _ in range(100)} == set(s1.worlds) | set(s2.worlds)


@pytest.mark.slow
def test_training_on_a_held_out_world_is_refused_in_one_line(tmp_path):
    import subprocess
    import sys

    from curlnav.builder import D4PGBuilder

    with pytest.raises(HeldOutSeedError, match="namo-office seed 300 is held out"):
        D4PGBuilder(ExperimentConfig(curriculum=CurriculumConfig(world="namo-office:300"))).make_env()
    with pytest.raises(HeldOutSeedError):
        WorldDraws().resolve("t-maze:100")  # an assignment naming one, in either mode
    result = subprocess.run([sys.executable, "-m", "curlnav.cli", "train", "--serial", "--world", "barn-3x3:150",
                             "--run-dir", str(tmp_path / "run"), "--minutes", "1"], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode != 0 and "barn-3x3 seed 150 is held out" in result.stderr
