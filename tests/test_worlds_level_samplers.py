"""Level samplers over a world distribution (issue 28): the paper's difficulty ordering (a
frontier of the easiest seeds that widens as the policy succeeds) and prioritized level replay
(seen levels replayed by learnability and staleness), the same in both training modes."""

from __future__ import annotations

import numpy as np
import pytest

from curlnav.worlds import levels as levels_module
from curlnav.worlds.difficulty.rank import rank
from curlnav.worlds.distribution import DistributionError, WorldDistribution, WorldDraws
from curlnav.worlds.levels import LevelSampler, difficulty_order

TMAZE = "t-maze-doors:0-19(levels=plr)"  # t-maze-doors worlds build and measure in milliseconds


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(levels_module, "_ORDERS", {})


def test_the_level_sampler_is_part_of_the_distributions_key_and_a_bad_one_is_refused():
    dist = WorldDistribution.from_spec({"family": "t-maze-doors", "seeds": [0, 19], "levels": "plr"})
    assert dist.key == TMAZE and WorldDistribution.parse(dist.key) == dist
    assert WorldDistribution.parse("t-maze-doors:0-19").levels == "uniform"
    with pytest.raises(DistributionError, match="levels must be one of uniform, difficulty, plr, got 'hardest'"):
        WorldDistribution.from_spec({"family": "t-maze-doors", "seeds": [0, 19], "levels": "hardest"})


def test_the_difficulty_order_is_the_papers_ranking_of_the_same_worlds_and_is_cached_on_disk(tmp_path, monkeypatch):
    dist = WorldDistribution.parse("t-maze-doors:0-11")
    order = difficulty_order(dist)
    # the independent truth: curlnav worlds rank (Table I's ranking) of the same twelve worlds
    by_name = {dist.world(s).name: s for s in dist.seeds}
    assert order == [by_name[row.name] for row in rank([dist.world(s) for s in dist.seeds])]
    assert sorted(order) == list(dist.seeds) and order != list(dist.seeds)
    # a second process reads the ranking from the cache instead of measuring again
    monkeypatch.setattr(levels_module, "_ORDERS", {})
    monkeypatch.setattr(levels_module, "_measure_order", lambda d: pytest.fail("measured again"))
    assert difficulty_order(dist) == order
    assert list((tmp_path / "cache" / "curlnav" / "levels").glob("t-maze-doors-*.json"))


def test_difficulty_draws_start_on_the_easiest_seeds_and_widen_as_the_policy_succeeds():
    dist = WorldDistribution.parse("t-maze-doors:0-39(levels=difficulty)")
    sampler = LevelSampler(dist, "difficulty")
    rng = np.random.default_rng(0)
    easiest = set(sampler.order[:10])
    assert sampler.frontier == 10
    failures = [sampler.draw(rng) for _ in range(200)]
    for seed in failures:
        sampler.record(seed, False)
    assert set(failures) <= easiest and sampler.frontier == 10  # failing: the frontier holds
    for _ in range(40):
        sampler.record(sampler.draw(rng), True)
    assert sampler.frontier == 18 and sampler.widened == 2  # every 20 successes widen it by 4 seeds


def test_plr_replays_the_levels_at_the_edge_of_what_the_policy_can_do():
    dist = WorldDistribution.parse("t-maze-doors:0-29(levels=plr,pool=2)")
    sampler = LevelSampler(dist, "plr", order=list(range(30)))
    sampler.frontier = 30
    rng = np.random.default_rng(1)
    chance = {s: (1.0 if s < 10 else 0.0 if s < 20 else 0.5) for s in range(30)}  # solved, hopeless, learnable
    outcomes = np.random.default_rng(2)
    counts = np.zeros(30)
    for i in range(3000):
        seed = sampler.draw(rng)
        sampler.record(seed, bool(outcomes.random() < chance[seed]))
        if i >= 500:
            counts[seed] += 1
    assert len(sampler.success) == 30  # every level was tried
    solved, hopeless, learnable = counts[:10].sum(), counts[10:20].sum(), counts[20:].sum()
    assert learnable > 2 * solved and learnable > 2 * hopeless, (solved, hopeless, learnable)
    assert counts.min() > 0  # staleness brings every level back now and then


def test_the_episode_loop_feeds_each_outcome_to_the_sampler_of_the_world_it_drew():
    from conftest import episode_loop, one_episode

    draws = WorldDraws(seed=[0, 1])
    loop = episode_loop("t-maze:0", draws)  # 3-step episodes: each ends unsuccessful
    try:
        names = [one_episode(loop, i, TMAZE) for i in range(6)]
        sampler = draws._samplers[TMAZE]
        seen = {f"t-maze-doors-{s}" for s in sampler.success}
        assert set(names) == seen and all(v == 0.0 for v in sampler.success.values())
        assert draws.levels(TMAZE)["seen"] == len(seen)
        one_episode(loop, 7, "t-maze:0")  # a plain world: its outcome is nobody's level
        assert set(sampler.success.values()) == {0.0} and draws.levels("t-maze-doors:0-19") is None
    finally:
        loop.close()
