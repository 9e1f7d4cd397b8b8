"""tare-l and dwa filter their scans as real stacks do (issue 37, deliverable 4): a short memory of
marked and cleared cells in the odometry frame, so that range noise, dropouts, spurious returns
and mislabelled runs of beams do not make them stop or steer into walls.

The truth is the geometry of a synthetic room (walls as segments, scans ray-cast against them);
the noise is made here, independently of the simulator's sensor models."""

from __future__ import annotations

import math

import numpy as np
import pytest

from curlnav.layout import ObservationLayout
from curlnav.nav.controllers.local import DynamicWindowPlanner, TareLocalPlanner
from curlnav.nav.perception.scan_filter import ScanFilterConfig, ScanMemory
from curlnav.sim import EnvConfig

CFG = EnvConfig()
ANGLES = np.linspace(-CFG.lidar_fov / 2, CFG.lidar_fov / 2, CFG.lidar_beams)
MAX_RANGE = CFG.lidar_max_range
# a 12 m x 7 m room with a wall across it at x = 6 that has a 1.6 m doorway (y 2.7..4.3), a pillar
# (0.4 m square) at (3, 5), walls as segments (x0, y0, x1, y1) in m
ROOM = np.array([
    (0, 0, 12, 0), (12, 0, 12, 7), (12, 7, 0, 7), (0, 7, 0, 0),
    (6, 0, 6, 2.7), (6, 4.3, 6, 7),
    (2.8, 4.8, 3.2, 4.8), (3.2, 4.8, 3.2, 5.2), (3.2, 5.2, 2.8, 5.2), (2.8, 5.2, 2.8, 4.8),
], dtype=np.float64)


def cast(pose: tuple[float, float, float]) -> np.ndarray:
    """Exact ranges (m) of the 241 beams from ``pose`` against ``ROOM``, ``MAX_RANGE`` where none."""
    x, y, yaw = pose
    d = np.stack([np.cos(yaw + ANGLES), np.sin(yaw + ANGLES)], axis=1)  # (B, 2)
    p0, p1 = ROOM[:, :2], ROOM[:, 2:]
    e = p1 - p0  # (W, 2)
    denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # (B, W)
    wx, wy = p0[None, :, 0] - x, p0[None, :, 1] - y
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (wx * e[None, :, 1] - wy * e[None, :, 0]) / denom
        u = (wx * d[:, None, 1] - wy * d[:, None, 0]) / denom
    hit = (np.abs(denom) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
    return np.minimum(np.where(hit, t, np.inf).min(axis=1), MAX_RANGE)


def wall_distance(points: np.ndarray) -> np.ndarray:
    """Distance (m) of each ``(n, 2)`` map point to the nearest wall of ``ROOM``."""
    p0, p1 = ROOM[None, :, :2], ROOM[None, :, 2:]
    e = p1 - p0
    t = np.clip(((points[:, None] - p0) * e).sum(-1) / (e * e).sum(-1), 0, 1)
    return np.hypot(*(points[:, None] - p0 - t[..., None] * e).transpose(2, 0, 1)).min(axis=1)


def noisy(ranges: np.ndarray, rng: np.random.Generator, sigma=0.04, dropout=0.04, spurious=0.02,
          dark=0.3) -> tuple[np.ndarray, np.ndarray]:
    """A real scanner's reading of ``ranges``: Gaussian range noise (``sigma`` m), dropouts to max
    range (a fraction ``dropout`` of the beams), spurious short returns (``spurious``; uniform
    short of the true range), and with probability ``dark`` a run of 12 beams returning nothing
    (a dark or glass surface)."""
    r = ranges.copy()
    back = r < MAX_RANGE
    r[back] = np.clip(r[back] + rng.normal(0, sigma, back.sum()), 0.0, MAX_RANGE)
    u = rng.random(len(r))
    r = np.where(u < spurious, rng.uniform(0.3, 1.0, len(r)) * r, r)
    r[(u >= spurious) & (u < spurious + dropout)] = MAX_RANGE
    if rng.random() < dark:
        start = int(rng.integers(0, len(r) - 12))
        r[start:start + 12] = MAX_RANGE
    return r, np.zeros(len(r))


def to_map(points: np.ndarray, pose) -> np.ndarray:
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return np.stack([x + c * points[:, 0] - s * points[:, 1], y + s * points[:, 0] + c * points[:, 1]], axis=1)


def raw_points(ranges: np.ndarray, labels: np.ndarray) -> np.ndarray:
    keep = (ranges < MAX_RANGE - 1e-3) & (labels < 0.5)
    return np.stack([ranges[keep] * np.cos(ANGLES[keep]), ranges[keep] * np.sin(ANGLES[keep])], axis=1)


def drive(steps: int = 30) -> list[tuple[float, float, float]]:
    """Poses of a robot crossing the room toward the doorway, turning a little (5 Hz, 0.2 m/step)."""
    return [(1.5 + 0.13 * k, 1.2 + 0.05 * k, 0.25 * math.sin(0.3 * k)) for k in range(steps)]


def scores(points_by_step, poses, reach) -> tuple[float, float]:
    """``(phantoms, gaps)`` over the run: obstacle points more than 0.2 m from every wall (per
    scan), and beams whose true wall within ``reach`` (m) has no obstacle point within 0.1 m of
    its true hit (a fraction of such beams)."""
    phantoms, gaps, walls = 0, 0, 0
    for points, pose in zip(points_by_step, poses):
        in_map = to_map(points, pose)
        phantoms += int((wall_distance(in_map) > 0.2).sum())
        truth = cast(pose)
        near = truth <= reach
        hits = to_map(np.stack([truth[near] * np.cos(ANGLES[near]), truth[near] * np.sin(ANGLES[near])], 1), pose)
        if len(in_map):
            d = np.hypot(hits[:, None, 0] - in_map[None, :, 0], hits[:, None, 1] - in_map[None, :, 1]).min(axis=1)
        else:
            d = np.full(len(hits), np.inf)
        gaps += int((d > 0.1).sum())
        walls += len(hits)
    return phantoms / len(poses), gaps / max(walls, 1)


def test_the_filtered_obstacles_match_the_true_walls_far_better_than_the_raw_scan():
    reach = ScanFilterConfig().range_m  # what the memory remembers
    raw_scores, filtered_scores = [], []
    for seed in range(4):  # four crossings of the room, each with its own noise
        rng = np.random.default_rng(seed)
        poses = drive()
        memory = ScanMemory(ANGLES, MAX_RANGE)
        raw, filtered = [], []
        for pose in poses:
            r, labels = noisy(cast(pose), rng)
            raw.append(raw_points(r, labels))
            filtered.append(memory.update(r, labels, pose))
        raw_scores.append(scores(raw, poses, reach))
        filtered_scores.append(scores(filtered, poses, reach))
    (raw_phantoms, raw_gaps), (phantoms, gaps) = np.mean(raw_scores, axis=0), np.mean(filtered_scores, axis=0)
    assert raw_phantoms >= 2.0, raw_phantoms  # the noise makes phantoms in the raw scan ...
    assert phantoms <= raw_phantoms / 5, (phantoms, raw_phantoms)  # ... the memory drops nearly all
    assert raw_gaps >= 0.003, raw_gaps  # dark surfaces open the walls ...
    assert gaps <= raw_gaps / 3, (gaps, raw_gaps)  # ... the memory closes them


def test_a_wall_a_segmenter_labels_movable_for_a_moment_stays_remembered():
    rng = np.random.default_rng(3)
    poses = drive(12)
    memory = ScanMemory(ANGLES, MAX_RANGE)
    for k, pose in enumerate(poses):
        truth = cast(pose)
        r, labels = noisy(truth, rng, spurious=0.0, dropout=0.0, dark=0.0)
        if k == len(poses) - 1:  # the last scan: the 25 beams of the nearest stretch of wall labelled movable
            start = int(np.argmin(np.convolve(truth, np.ones(25), "valid")))
            labels[start:start + 25] = 1.0
        points = memory.update(r, labels, pose)
    reach = memory.config.range_m
    _, gaps = scores([points], poses[-1:], reach)
    _, raw_gaps = scores([raw_points(r, labels)], poses[-1:], reach)
    assert gaps < 0.02 and raw_gaps > gaps, (gaps, raw_gaps)


def test_on_clean_scans_every_return_is_kept_and_nothing_phantom_is_added():
    poses = drive(20)
    memory = ScanMemory(ANGLES, MAX_RANGE)
    for pose in poses:
        r = cast(pose)
        points = memory.update(r, np.zeros_like(r), pose)
        newest = raw_points(r, np.zeros_like(r))
        np.testing.assert_allclose(points[:len(newest)], newest)  # the newest scan's returns, all of them
        assert (wall_distance(to_map(points, pose)) < 0.05).all()  # remembered ones lie on the walls too


def test_a_lone_return_counts_from_its_second_scan_and_a_beam_through_a_remembered_point_clears_it():
    memory = ScanMemory(ANGLES, MAX_RANGE)
    pose = (0.0, 0.0, 0.0)
    r = np.full(len(ANGLES), MAX_RANGE)
    r[120] = 2.0  # a thin leg straight ahead, seen by one beam
    assert len(memory.update(r, np.zeros_like(r), pose)) == 0  # once: could be a mixed pixel
    assert len(memory.update(r, np.zeros_like(r), pose)) == 1  # twice: an obstacle
    np.testing.assert_allclose(memory.update(np.full(len(ANGLES), MAX_RANGE), np.zeros_like(r), pose), [[2.0, 0.0]])
    # a dropout clears nothing (above); a return beyond it does: the space is free
    r[120] = 5.0
    points = memory.update(r, np.zeros_like(r), pose)
    assert not (np.hypot(points[:, 0] - 2.0, points[:, 1]) < 0.2).any(), points


def test_the_scan_filter_settings_are_checked():
    with pytest.raises(ValueError, match="votes"):
        ScanFilterConfig(scans=3, votes=4)
    with pytest.raises(ValueError, match="cell_m"):
        ScanFilterConfig(cell_m=0.0)


def observation(ranges: np.ndarray, labels: np.ndarray, pose, goal) -> np.ndarray:
    """The policy's observation with every frame the given one (goal in the map frame)."""
    lay = ObservationLayout.from_env_config(CFG)
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = c * (goal[0] - x) + s * (goal[1] - y), -s * (goal[0] - x) + c * (goal[1] - y)
    frame = [math.copysign(math.log1p(abs(dx)), dx), math.copysign(math.log1p(abs(dy)), dy), math.atan2(dy, dx)]
    return np.concatenate([np.tile(ranges, lay.range_frames), np.tile(labels, lay.label_frames),
                           np.tile(frame, lay.goal_frames)]).astype(np.float32)


@pytest.mark.parametrize("planner", [TareLocalPlanner, DynamicWindowPlanner], ids=["tare-l", "dwa"])
def test_the_planners_act_on_noisy_scans_nearly_as_on_clean_ones(planner):
    goal = (10.0, 3.5)  # through the doorway
    poses = drive()
    clean, filtered, raw = planner(CFG), planner(CFG), planner(CFG, scan_filter=None)
    for agent in (clean, filtered, raw):
        agent.reset(None, None)
    rng = np.random.default_rng(11)
    off_filtered, off_raw, stops = [], [], {"clean": 0, "filtered": 0, "raw": 0}
    for pose in poses:
        r = cast(pose)
        nr, nl = noisy(r, rng)
        info = {"pose": pose}
        a_clean = clean.act(observation(r, np.zeros_like(r), pose, goal), info)
        a_filtered = filtered.act(observation(nr, nl, pose, goal), info)
        a_raw = raw.act(observation(nr, nl, pose, goal), info)
        off_filtered.append(np.abs(a_filtered - a_clean)[:2].sum())
        off_raw.append(np.abs(a_raw - a_clean)[:2].sum())
        for name, a in (("clean", a_clean), ("filtered", a_filtered), ("raw", a_raw)):
            stops[name] += bool(a[0] == 0.0 and a[1] == 0.0)
    assert np.mean(off_filtered) <= 0.15, (np.mean(off_filtered), np.mean(off_raw))
    assert np.mean(off_filtered) < np.mean(off_raw), (np.mean(off_filtered), np.mean(off_raw))
    assert stops["filtered"] <= stops["clean"], stops


def test_a_late_scan_is_planned_in_the_frame_of_now():
    from curlnav.sim.config import SensorNoiseConfig

    late = CFG.replace(sensor_noise=SensorNoiseConfig("none", latency_steps=1))
    agent = DynamicWindowPlanner(late)
    agent.reset(None, None)
    before, now = (2.0, 2.0, 0.0), (2.2, 2.0, 0.3)
    r = cast(before)
    agent.sense(observation(r, np.zeros_like(r), before, (10.0, 3.5)), {"pose": before})
    points, gx, gy = agent.sense(observation(r, np.zeros_like(r), before, (10.0, 3.5)), {"pose": now})
    assert (wall_distance(to_map(points, now)) < 0.05).all()  # the scan of before, where the walls are now
    np.testing.assert_allclose(to_map(np.array([[gx, gy]]), now), [[10.0, 3.5]], atol=1e-5)


def test_a_scan_with_nothing_near_gives_no_obstacle_and_keeps_what_it_cannot_clear():
    memory = ScanMemory(ANGLES, MAX_RANGE)
    assert memory.update(np.full(len(ANGLES), MAX_RANGE), np.zeros(len(ANGLES)), (0.0, 0.0, 0.0)).shape == (0, 2)
    assert memory.update(np.full(len(ANGLES), 6.0), np.zeros(len(ANGLES)), (0.0, 0.0, 0.0)).shape == (241, 2)


def cast_with_ball(pose, ball: tuple[float, float], radius: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """``cast(pose)`` with a ball (a disc of ``radius`` m at ``ball``, map frame) in the room:
    exact ranges (m) and the segmenter's exact labels (1.0 on the beams that end on the ball)."""
    x, y, yaw = pose
    walls = cast(pose)
    d = np.stack([np.cos(yaw + ANGLES), np.sin(yaw + ANGLES)], axis=1)
    to_ball = np.array([ball[0] - x, ball[1] - y])
    along = d @ to_ball
    miss2 = to_ball @ to_ball - along ** 2
    with np.errstate(invalid="ignore"):
        t = along - np.sqrt(radius ** 2 - miss2)
    on_ball = (miss2 <= radius ** 2) & (t > 0) & (t < walls)
    return np.where(on_ball, t, walls), on_ball.astype(np.float64)


def test_a_ball_the_segmenter_misses_for_a_moment_is_no_obstacle_while_it_is_pushed():
    """A robot pushing a ball down the room: in one scan the segmenter labels the whole ball static
    (a missed object, as ``corrupt_scan`` draws them). The shield and the planners must not take it
    for a wall, in that scan or in the memory of the scans after it; the walls stay (every wall
    beam within reach is still covered)."""
    rng = np.random.default_rng(5)
    poses = [(1.5 + 0.15 * k, 3.5, 0.0) for k in range(14)]  # 5 Hz, 0.75 m/s toward the doorway's wall
    memory = ScanMemory(ANGLES, MAX_RANGE)
    missed_at = 6
    balls = []
    for k, pose in enumerate(poses):
        ball = (pose[0] + 0.75, pose[1])  # pushed: 0.75 m ahead of the base's centre
        balls.append(ball)
        exact, labels = cast_with_ball(pose, ball)
        r = np.clip(exact + rng.normal(0, 0.03, len(exact)) * (exact < MAX_RANGE), 0, MAX_RANGE)
        if k == missed_at:
            assert labels.sum() >= 5
            labels[:] = 0.0  # the ball's run of beams labelled static
        points = memory.update(r, labels, pose)
        if k >= missed_at:  # the missed scan, and the memory after it: nowhere the ball has been since,
            # outside the base (a point the base has driven over is ignored by the shield and the planners)
            in_map = to_map(points, pose)
            outside = (np.abs(points[:, 0]) > CFG.robot.base_length / 2) | (np.abs(points[:, 1]) > CFG.robot.base_width / 2)
            for where in balls[missed_at:]:
                on_ball = outside & (np.hypot(*(in_map - np.array(where)).T) < 0.25 + 0.1)
                assert not on_ball.any(), (k, where, in_map[on_ball])
    # the walls stay: every wall beam within the memory's reach that the ball does not hide is covered
    walls = cast(poses[-1])
    visible = (exact == walls) & (walls <= memory.config.range_m)
    assert visible.sum() >= 10
    hits = to_map(np.stack([walls[visible] * np.cos(ANGLES[visible]), walls[visible] * np.sin(ANGLES[visible])], 1),
                  poses[-1])
    d = np.hypot(hits[:, None, 0] - in_map[None, :, 0], hits[:, None, 1] - in_map[None, :, 1]).min(axis=1)
    assert (d <= 0.1).all(), hits[d > 0.1]


def test_a_wall_a_pushed_ball_runs_along_stays_an_obstacle():
    """A ball pushed along a wall (its surface 2 cm from the wall's face): the movable returns of
    the ball next to the static ones of the wall must not vote the wall away."""
    rng = np.random.default_rng(6)
    poses = [(1.5 + 0.15 * k, 0.75, 0.0) for k in range(10)]
    memory = ScanMemory(ANGLES, MAX_RANGE)
    for pose in poses:
        ball = (pose[0] + 0.75, 0.27)  # its surface 0.02 m from the wall y = 0
        exact, labels = cast_with_ball(pose, ball)
        r = np.clip(exact + rng.normal(0, 0.03, len(exact)) * (exact < MAX_RANGE), 0, MAX_RANGE)
        points = memory.update(r, labels, pose)
    in_map = to_map(points, poses[-1])
    walls = cast(poses[-1])
    visible = (exact == walls) & (walls <= memory.config.range_m) & (labels < 0.5)  # wall beams the ball does not hide
    assert visible.sum() >= 20
    hits = to_map(np.stack([walls[visible] * np.cos(ANGLES[visible]), walls[visible] * np.sin(ANGLES[visible])], 1),
                  poses[-1])
    d = np.hypot(hits[:, None, 0] - in_map[None, :, 0], hits[:, None, 1] - in_map[None, :, 1]).min(axis=1)
    assert (d <= 0.1).all(), hits[d > 0.1]
    # and the wall's own returns beside the ball, each of them, as measured in the newest scan
    beside = visible & (np.hypot(*(to_map(np.stack([walls * np.cos(ANGLES), walls * np.sin(ANGLES)], 1), poses[-1])
                                   - np.array(ball)).T) < 0.6)
    assert beside.sum() >= 3
    measured = np.stack([r[beside] * np.cos(ANGLES[beside]), r[beside] * np.sin(ANGLES[beside])], 1)
    kept = np.hypot(measured[:, None, 0] - points[None, :, 0], measured[:, None, 1] - points[None, :, 1]).min(axis=1)
    assert (kept < 1e-9).all(), measured[kept >= 1e-9]


def test_the_rescues_scan_map_keeps_no_wall_where_a_ball_was_missed_and_keeps_a_wall_mislabelled_movable():
    """The rescue plans on a map of its own scans (``curlnav.nav.global_planners.scan_map``). A ball the
    segmenter missed in two scans of ten must not become an occupied cell it plans round (it would
    route the robot away from the ball it should push); a wall it labelled movable in two scans of
    ten stays occupied."""
    from curlnav.nav.global_planners.scan_map import ScanMap, ScanMapConfig

    pose = (3.0, 1.5, 0.0)
    ball = (4.5, 2.2)  # ahead on the left, not hiding the wall straight ahead
    scan_map = ScanMap((6.0, 3.5), 14.0, ScanMapConfig(), ANGLES, MAX_RANGE)
    rng = np.random.default_rng(7)
    exact, on_ball = cast_with_ball(pose, ball)
    wall = (exact >= 2.9) & (exact < 3.2) & (np.abs(ANGLES) < 0.2)  # the wall at x = 6, straight ahead
    for k in range(10):
        r = np.clip(exact + rng.normal(0, 0.03, len(exact)) * (exact < MAX_RANGE), 0, MAX_RANGE)
        labels = on_ball.copy()
        if k in (3, 7):
            labels[on_ball > 0] = 0.0  # the ball missed
            labels[wall] = 1.0  # and the wall labelled movable
        scan_map.add_scan(r, labels, pose)
    occupied = scan_map.occupied
    iy, ix, _ = scan_map.cell_index(np.array([ball]) + np.array([[-0.25, 0.0]]))  # the ball's face
    near_ball = occupied[max(iy[0] - 3, 0):iy[0] + 4, max(ix[0] - 1, 0):ix[0] + 4]
    assert not near_ball.any()
    assert wall.sum() >= 5
    iy, ix, _ = scan_map.cell_index(np.array([[6.0, 1.5]]))
    assert occupied[iy[0] - 1:iy[0] + 2, ix[0] - 1:ix[0] + 2].any()
