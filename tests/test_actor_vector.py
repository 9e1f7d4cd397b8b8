"""One actor process stepping K environments with one batched policy call (issue 31): what
reaches the replay is exactly what the K environments saw, frame stacks included, and each
environment keeps its own episodes and assignment."""

from __future__ import annotations

import numpy as np
import pytest

from curlnav.actor.vector import VectorEpisodeLoop, VectorNStepWriter
from curlnav.config import D4PGConfig
from curlnav.layout import ObservationLayout
from curlnav.learner.networks import BehaviourPolicy
from curlnav.replay import ReplayTable
from curlnav.sim import EnvConfig, NamoEnv


def test_the_replay_rebuilds_exactly_what_each_of_k_environments_observed():
    cfg = EnvConfig(max_episode_steps=9, end_on_base_collision=False)
    layout = ObservationLayout.from_env_config(cfg)
    k = 3
    rng = np.random.default_rng(5)
    seen = {}  # action bytes -> (environment, observation it was taken at): the environments' own truth
    history = [[] for _ in range(k)]  # per environment: the observations its actions were taken at
    calls = []

    def policy(obs: np.ndarray) -> np.ndarray:  # one call for all running environments
        running = [e for e, o in enumerate(loop.obs) if o is not None]
        actions = rng.uniform([0, -1, 0], [1, 1, 1], size=(len(obs), 3)).astype(np.float32)
        calls.append(len(obs))
        for e, o, a in zip(running, obs, actions):
            seen[a.tobytes()] = (e, len(history[e]))
            history[e].append(o.copy())
        return actions

    loop = VectorEpisodeLoop([NamoEnv("open-room", cfg) for _ in range(k)], policy,
                             VectorNStepWriter(layout, k, n_step=1, discount=0.9))
    table = ReplayTable(layout, max_size=10_000)
    episodes = [0] * k
    try:
        for _ in range(40):
            for e in loop.waiting():
                history[e].append(None)  # an episode boundary: no next observation across it
                loop.begin(e, seed=100 * e + episodes[e], options={"world": "open-room"})
            for e, end in loop.step():
                episodes[e] += 1
                assert end.info["steps"] == 9
            table.insert(loop.flush(), stream="actor-0")  # K streams under one actor id, as on the wire
    finally:
        loop.close()
    assert calls == [k] * 40 and episodes == [4, 4, 4]
    assert table.size == 40 * k
    sample = table.sample(300)
    checked_next = 0
    for i in range(300):
        e, j = seen[sample.action[i].tobytes()]
        obs = history[e][j]
        assert np.allclose(sample.obs[i], obs, rtol=2e-3, atol=2e-3), "a frame stack mixed environments"
        if j + 1 < len(history[e]) and history[e][j + 1] is not None:
            assert np.allclose(sample.next_obs[i], history[e][j + 1], rtol=2e-3, atol=2e-3)
            assert np.isclose(sample.discount[i], 0.9)
            checked_next += 1
    assert checked_next > 200


def test_a_batched_behaviour_policy_acts_as_k_single_calls():
    layout = ObservationLayout()
    d4pg = D4PGConfig()
    single = BehaviourPolicy(layout, d4pg, sigma=0.0, warmup_steps=0, rng=np.random.default_rng(0))
    batched = BehaviourPolicy(layout, d4pg, sigma=0.0, warmup_steps=0, rng=np.random.default_rng(0))
    from curlnav.learner.networks import Actor

    network = Actor(layout, d4pg)
    network.eval()
    single.use_network(network)
    batched.use_network(network)
    obs = np.random.default_rng(1).uniform(0, 5, size=(6, layout.size)).astype(np.float32)
    assert np.allclose(batched.batch(obs), np.stack([single(o) for o in obs]), atol=1e-5)
    assert batched.steps == single.steps == 6
    noisy = BehaviourPolicy(layout, d4pg, sigma=0.3, warmup_steps=0, rng=np.random.default_rng(0))
    noisy.use_network(network)
    actions = noisy.batch(obs)
    assert actions.shape == (6, 3) and not np.allclose(actions, batched.batch(obs))
    warm = BehaviourPolicy(layout, d4pg, sigma=0.3, warmup_steps=10, rng=np.random.default_rng(0))
    assert warm.batch(obs).shape == (6, 3) and warm.steps == 6  # random actions in the warm-up


def test_bench_actor_prints_steps_per_second_and_the_ratio_to_the_bare_environment():
    from curlnav.bench.actor import run_actor_bench

    lines = []
    rows = run_actor_bench("t-maze:0", envs=(1, 2), steps=60, episode_steps=20, say=lines.append)
    assert [r.envs for r, _ in rows] == [1, 2] and all(r.steps >= 60 and ratio > 0 for r, ratio in rows)
    assert lines[1].startswith("bare environment") and "steps/s" in lines[1]
    assert all("steps/s  ratio" in line for line in lines[2:4]) and lines[-1].startswith("best: ")


@pytest.mark.net
@pytest.mark.slow
def test_a_run_whose_actor_steps_three_environments_trains_and_loses_nothing(tmp_path):
    import json

    from conftest import wait_for

    from curlnav.config import resolve_config
    from curlnav.run.launch import LocalCluster

    experiment = resolve_config(overrides=["actor.envs_per_process=3", "replay.min_size=200",
                                           "replay.samples_per_insert=8", "d4pg.batch_size=128"], environ={})
    cluster = LocalCluster(tmp_path / "run", experiment, actors=1, run="vector",
                           extra={"learner": ["--publish-every", "5"]})
    cluster.start()
    try:
        status = cluster.status
        s = wait_for("episodes from the 3-environment actor and learner version >= 2", lambda: (
            (st := status()) and (st["learner"]["version"] or 0) >= 2 and st["replay"]["size"]
            and sum(a.get("episodes", 0) for a in st["live_actors"].values()) >= 6 and st), timeout=300)
        assert set(s["live_actors"]) == {"actor-0"}
    finally:
        cluster.stop()
    final = json.loads((tmp_path / "run" / "actors" / "actor-0" / "actor-final.json").read_text())
    assert final["generated"] > 0 and final["unacknowledged_transitions"] == 0, final


def test_eight_environments_with_five_step_returns_lose_no_transition_and_keep_their_frame_stacks():
    """The default actor (8 environments, n-step 5, a batch every 24 environment steps, episodes
    ending at different times): the replay holds every transition the writer made, none dropped
    for a frame it no longer knows, and each observation is its own environment's frame stack."""
    from conftest import REPLAY_LAYOUT as L
    from conftest import expected_stack, obs_for

    k, rng = 8, np.random.default_rng(5)
    writer = VectorNStepWriter(L, k, n_step=5, discount=0.99)
    table = ReplayTable(L, max_size=50_000)
    episode, step, length = [0] * k, [0] * k, [int(rng.integers(3, 40)) for _ in range(k)]
    for e in range(k):
        writer[e].first(obs_for(0, episode=100 * e))
    made = since_batch = 0
    for _ in range(600):
        for e in range(k):
            step[e] += 1
            done = step[e] == length[e]
            # the action names (environment, episode, step of the observation it was taken at)
            writer[e].step(np.array([e, episode[e], step[e] - 1], np.float32), 1.0,
                           obs_for(step[e], episode=100 * e + episode[e]), done, False)
            since_batch += 1
            if done:
                episode[e] += 1
                step[e], length[e] = 0, int(rng.integers(3, 40))
                writer[e].first(obs_for(0, episode=100 * e + episode[e]))
            if since_batch >= 24:
                batch = writer.flush()
                made += batch.num_transitions
                table.insert(batch, stream="actor-0")
                since_batch = 0
    batch = writer.flush()
    made += batch.num_transitions
    table.insert(batch, stream="actor-0")
    assert table.dropped == {} and table.size == made > 3000
    sample = table.sample(200)
    for i in range(200):
        e, ep, t = (int(x) for x in sample.action[i])
        assert np.allclose(sample.obs[i], expected_stack(list(range(t + 1)), 100 * e + ep), atol=1e-2)


def test_an_actor_process_keeps_no_more_scenes_built_than_its_budget():
    """Each kept scene is its own PyBullet client (20-30 MB on a NAMO floor): an actor of K
    environments drawing fresh worlds every episode holds at most ``scenes`` of them, not K x the
    draws' 16 (one actor grew to 9 GB that way)."""
    from curlnav.worlds.distribution import WorldDraws

    cfg = EnvConfig(max_episode_steps=2, end_on_base_collision=False)
    layout = ObservationLayout.from_env_config(cfg)
    k, budget = 3, 6
    draws = WorldDraws(seed=0)
    loop = VectorEpisodeLoop([NamoEnv("open-room", cfg) for _ in range(k)],
                             lambda obs: np.tile(np.float32([0.0, 0.0, 0.0]), (len(obs), 1)),
                             VectorNStepWriter(layout, k, n_step=1, discount=0.9), draws, scenes=budget)
    built = lambda env: len(env._scenes) + (env._scene is not None)  # noqa: E731
    try:
        for episode in range(12):
            for e in loop.waiting():
                loop.begin(e, seed=episode, options={"world": "t-maze:0-29"})  # a fresh world each episode
            loop.step()
            loop.step()
        assert draws.generated >= 10, "the draws gave fresh worlds"
        assert sum(built(env) for env in loop.envs) <= budget
        assert all(built(env) == budget // k for env in loop.envs), "each environment keeps its share"
    finally:
        loop.close()
