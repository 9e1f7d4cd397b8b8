"""The network's memory (issue 53, ``curlnav.memory``): recent static returns kept in the
odometry frame and read as a ring round the robot. A user would see it break as a network that
forgets the wall it just turned away from, a ring that points the wrong way after the robot
turned or drove, a pushed ball remembered as a wall, or a replay, a wire message, an artefact or
an evaluation that drops or misplaces the ring."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from curlnav.actor.vector import VectorEpisodeLoop, VectorNStepWriter
from curlnav.builder import D4PGBuilder
from curlnav.config import ConfigError, ExperimentConfig, MemoryConfig
from curlnav.layout import ObservationLayout, beam_angles
from curlnav.memory import MemoryObserver, RememberingPolicy, ScanMemory, remembering
from curlnav.proto.codec import ProtoError
from curlnav.proto.messages import SampledBatch, TransitionBatch
from curlnav.replay.table import ReplayTable

ROOT = Path(__file__).resolve().parent.parent
T_MAZE = str(ROOT / "scheduler/curricula/worlds/t-maze-0.yaml")
FOV = math.radians(240.0)
LAYOUT = ObservationLayout(memory_beams=72, memory_range=8.0, memory_steps=30, memory_stride=1)


def wall_scan(pose: tuple[float, float, float], wall_x: float, labels: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The 241 ranges a LiDAR at ``pose`` reads of an endless wall at ``x = wall_x`` (m): an
    independent ray cast, clipped at 10 m."""
    x, y, yaw = pose
    angles = beam_angles(FOV, 241) + yaw
    with np.errstate(divide="ignore"):
        t = (wall_x - x) / np.cos(angles)
    ranges = np.where((t > 0) & np.isfinite(t), t, 10.0)
    return np.minimum(ranges, 10.0), np.full(241, labels)


def sector_at(bearing: float, sectors: int = 72) -> int:
    """The ring's sector round ``bearing`` (rad, robot frame): sector 0 straight back."""
    return round((bearing + math.pi) / (2 * math.pi / sectors)) % sectors


def test_a_wall_turned_away_from_stays_in_the_ring_behind_the_robot():
    memory = ScanMemory(LAYOUT, FOV)
    start = (0.0, 0.0, 0.0)
    memory.add(*wall_scan(start, 2.0), start)
    ahead = memory.ring(start)
    assert ahead[sector_at(0.0)] == pytest.approx(2.0, abs=0.02)  # the wall, 2 m ahead
    assert ahead[sector_at(math.pi)] == 8.0  # nothing known behind
    turned = (0.0, 0.0, math.pi)
    memory.add(*wall_scan(turned, 2.0), turned)  # the LiDAR (240 deg) now faces away: it sees no wall
    ring = memory.ring(turned)
    assert ring[sector_at(math.pi)] == pytest.approx(2.0, abs=0.02)  # remembered, straight behind
    assert ring[sector_at(0.0)] == 8.0
    # 45 deg off the wall's normal the nearest remembered return is 2 / cos(45 deg) away, within a sector
    assert ring[sector_at(math.pi - math.pi / 4)] == pytest.approx(2.0 / math.cos(math.pi / 4), rel=0.06)


def test_the_ring_follows_the_odometry_as_the_robot_drives():
    memory = ScanMemory(LAYOUT, FOV)
    memory.add(*wall_scan((0.0, 0.0, 0.0), 3.0), (0.0, 0.0, 0.0))
    nearer = (1.5, 0.4, math.pi / 2)  # drove 1.5 m toward the wall, now facing left of it
    memory.add(np.full(241, 10.0), np.zeros(241), nearer)
    ring = memory.ring(nearer)
    assert ring[sector_at(-math.pi / 2)] == pytest.approx(1.5, abs=0.02)  # the wall on the robot's right


def test_returns_labelled_movable_are_not_remembered_and_old_ones_are_forgotten():
    memory = ScanMemory(LAYOUT, FOV)
    pose = (0.0, 0.0, 0.0)
    memory.add(*wall_scan(pose, 2.0, labels=1.0), pose)  # a pushed ball, say: the live scan shows it
    assert np.all(memory.ring(pose) == 8.0)
    memory.add(*wall_scan(pose, 2.0), pose)
    for _ in range(LAYOUT.memory_steps - 1):
        memory.add(np.full(241, 10.0), np.zeros(241), pose)
        assert memory.ring(pose).min() == pytest.approx(2.0, abs=0.02)  # kept memory_steps steps ...
    memory.add(np.full(241, 10.0), np.zeros(241), pose)
    assert np.all(memory.ring(pose) == 8.0)  # ... then forgotten
    memory.add(*wall_scan(pose, 2.0), pose)
    memory.reset()
    assert np.all(memory.ring(pose) == 8.0)


def test_memory_settings_out_of_range_are_refused_in_one_line():
    for bad in ({"beams": -1}, {"range_m": 0.0}, {"steps": 0}, {"stride": 10, "steps": 5}, {"beams": True}):
        with pytest.raises(ConfigError, match=r"memory\.") as caught:
            MemoryConfig(**bad)
        assert "\n" not in str(caught.value)
    with pytest.raises(ValueError, match="memory_beams"):
        ObservationLayout(memory_beams=10**6)


def memory_experiment(world: str = T_MAZE) -> ExperimentConfig:
    experiment = dataclasses.replace(ExperimentConfig(), memory=MemoryConfig(beams=36, steps=60, stride=2))
    return dataclasses.replace(experiment, curriculum=dataclasses.replace(experiment.curriculum, world=world))


def test_an_actor_writes_each_frame_with_its_ring_and_the_replay_gives_it_back(tmp_path):
    experiment = memory_experiment()
    builder = D4PGBuilder(experiment)
    layout = builder.layout
    assert layout.size == builder.config.env.observation_size + 36
    seen: list[np.ndarray] = []

    def ahead(observations: np.ndarray) -> np.ndarray:
        seen.extend(observations.copy())
        return np.tile(np.array([0.6, 0.3, 0.0], np.float32), (len(observations), 1))

    writer = VectorNStepWriter(layout, 2, n_step=1, discount=0.99)
    loop = VectorEpisodeLoop([builder.make_env() for _ in range(2)], ahead, writer, memory=builder.make_memories(2))
    table = ReplayTable(layout, 1000)
    try:
        for k in range(2):
            loop.begin(k, seed=k, options={"world": T_MAZE, "pair": "p4"})
        for _ in range(25):
            loop.step()
            for k in loop.waiting():
                loop.begin(k, seed=50 + k, options={"world": T_MAZE, "pair": "p4"})
        batch = loop.flush()
    finally:
        loop.close()
    assert all(len(obs) == layout.size for obs in seen)
    rings = np.array([layout.ring_of(obs) for obs in seen])
    assert rings.min() < 7.0  # the T-maze's walls are remembered ...
    assert np.all(rings <= 8.0)
    assert batch.memory.shape == (batch.num_frames, 36)
    decoded = TransitionBatch.decode(TransitionBatch("a", 0, 0, batch).encode(), beams=241, memory_beams=36).batch
    np.testing.assert_array_equal(decoded.memory, batch.memory)
    with pytest.raises(ProtoError, match="memory"):
        TransitionBatch.decode(TransitionBatch("a", 0, 0, batch).encode(), beams=241, memory_beams=72)
    table.insert(decoded, force=True)
    sample = table.sample(16, timeout=0)
    assert sample.obs.shape == (16, layout.size)
    # every sampled observation is one the network saw, ring included (float16 in the replay)
    for obs in sample.obs:
        assert min(np.abs(np.array(seen) - obs).max(axis=1)) < 0.01
    restored = ReplayTable.restore(table.save(tmp_path / "replay.npz"))
    frames = restored.sample_frames(8, timeout=0)
    assert frames["obs_memory"].shape == (8, 36)
    message = SampledBatch.decode(SampledBatch.writer(8, layout).payload(), layout)
    assert message.obs_memory.shape == (8, 36) and message.obs().shape == (8, layout.size)


def test_a_trained_network_with_memory_ships_and_evaluates_with_its_ring(tmp_path):
    from curlnav.evaluation.protocol import evaluate
    from curlnav.learner.artefact import export_policy
    from curlnav.nav import build_stack, parse_agent
    from curlnav.policy import PolicyArtefact

    experiment = memory_experiment()
    builder = D4PGBuilder(experiment)
    state = builder.make_learner_state(device="cpu")
    folder = export_policy(state, tmp_path / "policy", experiment.env, worlds=[T_MAZE], env_steps=0)
    policy = PolicyArtefact(folder)
    assert policy.metadata["observation"]["layout"]["memory_beams"] == 36
    assert policy.observation_size == builder.layout.size
    _, agent = build_stack(parse_agent(str(folder) + "+bare"), experiment.eval_env,
                           lambda path: PolicyArtefact(path))
    assert isinstance(agent, RememberingPolicy)
    result = evaluate(agent, T_MAZE, ["p4"], experiment.eval_env)
    assert result.episodes == 1
    with pytest.raises(ValueError, match="act\\(observation, info\\)"):
        agent(np.zeros(experiment.env.observation_size, np.float32))
    # a policy without memory is left as it is; a network fed a ring built here acts as the wrapper does
    assert remembering(lambda obs: obs, FOV) is not None
    observer = MemoryObserver(builder.layout, FOV)
    env_obs = np.full(experiment.env.observation_size, 5.0, np.float32)
    full = observer(env_obs, {"odometry": (0.0, 0.0, 0.0)})
    np.testing.assert_allclose(agent.policy(full), policy(full))


def test_a_long_drive_keeps_what_a_plain_dictionary_of_cells_keeps():
    """The hash table (which grows, and drops forgotten cells when it is rebuilt) against an
    independent memory of the same rule written plainly: a dict from 0.1 m cell to its newest
    return and step, and every remembered return checked against every sector."""
    layout = ObservationLayout(memory_beams=72, memory_range=8.0, memory_steps=100, memory_stride=2)
    memory = ScanMemory(layout, FOV)
    rng = np.random.default_rng(3)
    angles = beam_angles(FOV, 241)
    cells: dict[tuple[int, int], tuple[float, float, int]] = {}
    pose = np.array([0.0, 0.0, 0.0])
    checked = 0
    for step in range(400):  # a random walk among random returns: thousands of cells in all
        pose += [0.15 * math.cos(pose[2]), 0.15 * math.sin(pose[2]), rng.uniform(-0.3, 0.3)]
        ranges = np.minimum(rng.uniform(0.5, 12.0, 241), 10.0)
        labels = (rng.uniform(size=241) < 0.1).astype(float)  # a tenth called movable: never remembered
        memory.add(ranges, labels, tuple(pose))
        if step % 2 == 0:
            for r, label, a in zip(ranges[::2], labels[::2], angles[::2]):
                if r < 10.0 - 1e-3 and label < 0.5:
                    px, py = pose[0] + r * math.cos(a + pose[2]), pose[1] + r * math.sin(a + pose[2])
                    cells[(math.floor(px / 0.1), math.floor(py / 0.1))] = (px, py, step)
        if step % 7 == 0:
            expected = [8.0] * 72
            for px, py, seen in cells.values():
                if seen > step - layout.memory_steps:
                    dx, dy = px - pose[0], py - pose[1]
                    ahead = math.cos(pose[2]) * dx + math.sin(pose[2]) * dy
                    left = -math.sin(pose[2]) * dx + math.cos(pose[2]) * dy
                    k = math.floor((math.atan2(left, ahead) + math.pi + math.pi / 72) / (2 * math.pi / 72)) % 72
                    expected[k] = min(expected[k], math.hypot(ahead, left))
            np.testing.assert_allclose(memory.ring(tuple(pose)), expected, atol=1e-5)
            checked += 1
    assert checked > 50 and memory.cells > 500 and len(memory._seen) > 4096  # the table grew past its first size


def test_the_barn_suite_builds_a_jackal_memory_from_the_scan_the_policy_reads(tmp_path):
    """On the BARN suite the Jackal policy reads 271 of the UST-10LX's 1081 beams
    (``ResampledScanPolicy``): its memory is built from those 271, and its network gets the ring."""
    from curlnav.evaluation.barn import ResampledScanPolicy, jackal_env_config, policy_loader
    from curlnav.evaluation.protocol import evaluation_config
    from curlnav.learner.artefact import export_policy, load_policy
    from curlnav.sim import NamoEnv
    from curlnav.sim.robots import load_profile

    profile = load_profile("jackal")
    experiment = dataclasses.replace(ExperimentConfig(), robot="jackal", env=profile.apply(ExperimentConfig().env),
                                     memory=MemoryConfig(beams=72))
    builder = D4PGBuilder(experiment)
    folder = export_policy(builder.make_learner_state(device="cpu"), tmp_path / "jackal", experiment.env,
                           worlds=["barn-course:0"], env_steps=0)
    suite = jackal_env_config(evaluation_config())
    policy = policy_loader(suite, load_policy)(str(folder))
    assert isinstance(policy, ResampledScanPolicy) and isinstance(policy.policy, RememberingPolicy)
    assert policy.policy.observer.memory.layout.beams == 271
    seen = []
    network = policy.policy.policy
    policy.policy.policy = lambda obs: seen.append(obs) or network(obs)
    env = NamoEnv("barn-course:90", suite)
    try:
        obs, info = env.reset(seed=0)
        policy.reset(env.world, env.pair)
        for _ in range(5):
            obs, _, terminated, truncated, info = env.step(policy.act(obs, info))
            if terminated or truncated:
                break
    finally:
        env.close()
    assert seen and all(len(o) == builder.layout.size for o in seen)
    assert builder.layout.ring_of(seen[-1]).min() < 8.0  # the course's cylinders are remembered


def test_a_memory_run_starts_only_from_a_policy_with_the_same_memory(tmp_path):
    """``--init-from``: the run's layout, memory included, must be the source's (one line)."""
    from curlnav.learner.artefact import export_policy
    from curlnav.learner.init_from import check_starting_point, find_starting_point

    plain, remembering_one = dataclasses.replace(ExperimentConfig()), memory_experiment("open-room")
    folders = {}
    for name, experiment in (("plain", plain), ("memory", remembering_one)):
        state = D4PGBuilder(experiment).make_learner_state(device="cpu")
        folders[name] = export_policy(state, tmp_path / name, experiment.env, worlds=["open-room"], env_steps=0)
    check_starting_point(find_starting_point(str(folders["memory"])), remembering_one)
    check_starting_point(find_starting_point(str(folders["plain"])), plain)
    for source, run in (("plain", remembering_one), ("memory", plain)):
        with pytest.raises(ValueError, match="observation layout") as caught:
            check_starting_point(find_starting_point(str(folders[source])), run)
        assert "\n" not in str(caught.value)
    with pytest.raises(ConfigError, match="memory.beams is 0"):
        MemoryConfig(range_m=5.0)


def test_under_latency_each_scan_is_remembered_where_it_was_sensed():
    """With ``latency_steps`` the newest scan is that old; the memory places it at the odometry
    pose it was sensed from (``info["observed_odometry"]``), not at the odometry of now."""
    from curlnav.sim import NamoEnv
    from curlnav.sim.config import SensorNoiseConfig

    experiment = ExperimentConfig()
    env_config = experiment.eval_env.replace(sensor_noise=SensorNoiseConfig(preset="realistic", latency_steps=2))
    env = NamoEnv("open-room", env_config)
    layout = ObservationLayout.of(env_config, MemoryConfig(beams=72, stride=1))
    by_sensed, by_now = ScanMemory(layout, env_config.lidar_fov), ScanMemory(layout, env_config.lidar_fov)
    observer = MemoryObserver(layout, env_config.lidar_fov)
    try:
        obs, info = env.reset(seed=1)
        moved = 0.0
        for _ in range(8):
            ring = layout.ring_of(observer(obs, info))
            ranges, labels, _ = ObservationLayout.from_env_config(env_config).newest_frame(obs)
            by_sensed.add(ranges, labels, info["observed_odometry"])
            by_now.add(ranges, labels, info["odometry"])
            np.testing.assert_allclose(ring, by_sensed.ring(info["observed_odometry"]), atol=1e-5)
            moved = max(moved, float(np.abs(by_now.ring(info["odometry"]) - ring).max()))
            obs, _, _, _, info = env.step([0.2, 1.0, 0.0])  # turning on the spot
    finally:
        env.close()
    assert moved > 0.05  # placed at the pose of now, the remembered walls would have turned with the robot


def test_a_checkpoint_is_not_resumed_into_a_run_that_reads_another_observation():
    """A learner or ``--serial`` run resumed with the memory toggled is refused in one line."""
    from curlnav.learner.d4pg import check_resumed_layout

    state = D4PGBuilder(memory_experiment("open-room")).make_learner_state(device="cpu")
    check_resumed_layout(state, state.layout, "latest.safetensors", "run folder")
    with pytest.raises(ConfigError, match="latest.safetensors was trained on another observation") as caught:
        check_resumed_layout(state, D4PGBuilder(ExperimentConfig()).layout, "latest.safetensors", "run folder")
    assert "\n" not in str(caught.value)
