"""The ROS 2 node reads a scan's special values as training sees them (issue 37): per REP 117,
+inf (and beyond range_max) is no return, the simulator's max range; -inf (and below range_min)
is too close, range_min; NaN is an erroneous measurement, read as no return while rare and
refused when the sensor gives many."""

from __future__ import annotations

import math
from types import SimpleNamespace as ns

import numpy as np
import pytest

from curlnav.ros2.node import MAX_NAN_FRACTION, NodeConfig, PolicyNode, ScanLayout, ScanRefused, resample_scan

INF, NAN = math.inf, math.nan


def scan_of(ranges, labels=None, range_min=0.0, range_max=10.0, fov=math.radians(240)):
    n = len(ranges)
    return ns(header=ns(frame_id="base_link"), angle_min=-fov / 2, angle_max=fov / 2, angle_increment=fov / (n - 1),
              range_min=range_min, range_max=range_max, ranges=list(ranges),
              intensities=list(labels if labels is not None else [0.0] * n))


def odom_of(x, y, yaw):
    return ns(header=ns(frame_id="odom"), pose=ns(pose=ns(position=ns(x=x, y=y),
                                                         orientation=ns(x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                                        w=math.cos(yaw / 2)))))


def test_special_ranges_read_as_the_simulator_gives_them():
    layout = ScanLayout()  # 241 beams, 10 m: the simulator's LiDAR
    ranges = np.full(241, 5.0)
    labels = np.zeros(241)
    ranges[10], ranges[11] = INF, 25.0  # no return; beyond range_max (20 m): no return
    ranges[12] = 15.0  # a return beyond the policy's 10 m: clipped there, as the simulator clips
    ranges[20], ranges[21] = -INF, 0.03  # too close; below range_min (0.06 m): too close
    ranges[30], labels[30] = NAN, 1.0  # erroneous: no return, and no label
    labels[40] = 1.0
    r, lab = resample_scan(scan_of(ranges, labels, range_min=0.06, range_max=20.0), layout)
    assert r[10] == r[11] == r[12] == layout.max_range_m == 10.0
    assert r[20] == r[21] == pytest.approx(0.06)
    assert r[30] == 10.0 and lab[30] == 0.0
    assert lab[40] == 1.0 and lab.sum() == 1.0
    assert np.all(np.delete(r, [10, 11, 12, 20, 21, 30]) == 5.0)
    # a scan without range_min (or 0): too close reads 0, as before
    r, _ = resample_scan(scan_of([-INF] + [5.0] * 240), layout)
    assert r[0] == 0.0


def test_a_few_nan_ranges_read_as_no_return_and_many_are_refused():
    layout = ScanLayout()
    allowed = int(MAX_NAN_FRACTION * 241)  # 12 of 241 at 5 %
    ranges = np.full(241, 5.0)
    ranges[:allowed] = NAN
    r, _ = resample_scan(scan_of(ranges), layout)
    assert np.all(r[:allowed] == 10.0) and np.all(r[allowed:] == 5.0)
    ranges[allowed] = NAN
    with pytest.raises(ScanRefused, match=f"too many NaN ranges: {allowed + 1} of 241"):
        resample_scan(scan_of(ranges), layout)
    with pytest.raises(ScanRefused, match="too many NaN"):
        resample_scan(scan_of([NAN] * 241), layout)
    with pytest.raises(ScanRefused, match="too many NaN"):  # the strict reading: any NaN refused
        resample_scan(scan_of([5.0] * 120 + [NAN] + [5.0] * 120), layout, max_nan_fraction=0.0)
    with pytest.raises(ValueError, match="max_nan_fraction"):
        NodeConfig(max_nan_fraction=1.5)


def test_the_node_drives_on_through_an_occasional_nan_and_stops_on_a_failing_sensor():
    node = PolicyNode(lambda obs: np.array([1.0, 0.0, 0.0]))
    node.on_goal(ns(header=ns(frame_id="odom"), pose=ns(position=ns(x=5.0, y=0.0))))
    node.on_odom(odom_of(0.0, 0.0, 0.0), 0.0)
    one_nan = [5.0] * 120 + [NAN] + [5.0] * 120
    assert node.on_scan(scan_of(one_nan), 0.0) and node.act(0.0).linear == 1.0
    failing = [NAN if k % 4 == 0 else 5.0 for k in range(241)]  # a quarter of the beams
    assert not node.on_scan(scan_of(failing), 0.1)
    command = node.act(0.1)
    assert command.is_stop and node.state.startswith("stopped: refused /scan (too many NaN ranges")
    assert node.counts["scans_refused: too many NaN ranges"] == 1
    assert node.on_scan(scan_of(one_nan), 0.2) and node.act(0.2).linear == 1.0  # a good scan: on again
    strict = PolicyNode(lambda obs: np.array([1.0, 0.0, 0.0]), config=NodeConfig(max_nan_fraction=0.0))
    assert not strict.on_scan(scan_of(one_nan), 0.0)


def test_the_node_builds_the_simulators_observation_from_a_scan_with_inf_nan_and_far_returns():
    """NamoEnv with a 3 m LiDAR in the open room: many beams return nothing. A robot's scanner
    reports them as +inf, NaN (a few) or a return beyond 3 m (its own range_max is 30 m); the
    node must give the policy exactly what the simulator gives."""
    from curlnav.sim import EnvConfig, NamoEnv

    cfg = EnvConfig(lidar_max_range=3.0)
    layout = ScanLayout.from_env_config(cfg)
    seen = []
    node = PolicyNode(lambda obs: seen.append(obs) or np.array([0.6, 0.3, 0.0]), layout)
    env = NamoEnv("open-room", cfg)
    rng = np.random.default_rng(37)
    try:
        obs, info = env.reset(seed=3, options={"pair": "diagonal"})
        node.on_goal(ns(header=ns(frame_id="odom"), pose=ns(position=ns(x=env.pair.gx, y=env.pair.gy))))
        specials = 0
        for step in range(12):
            sim_ranges = obs[3 * 241:4 * 241].astype(np.float64)
            none = np.flatnonzero(sim_ranges >= cfg.lidar_max_range)
            assert len(none) > 20, "the test needs beams that return nothing"
            ranges, labels = sim_ranges.copy(), env.last_labels.astype(np.float64).copy()
            kind = rng.integers(0, 3, len(none))
            ranges[none[kind == 0]] = INF
            ranges[none[kind == 1]] = rng.uniform(3.5, 30.0, (kind == 1).sum())
            nan = none[kind == 2][:int(MAX_NAN_FRACTION * 241)]
            ranges[nan], labels[nan] = NAN, NAN  # a driver's NaN, its intensity too
            specials += len(none)
            node.on_scan(scan_of(ranges, labels, range_min=0.05, range_max=30.0), now=float(step))
            node.on_odom(odom_of(*info["pose"]), now=float(step))
            command = node.act(float(step))
            assert not command.is_stop, node.state
            np.testing.assert_allclose(seen[-1], obs, atol=2e-6, err_msg=f"step {step}")
            obs, _, _, _, info = env.step([command.linear / cfg.robot.max_linear_speed,
                                           command.angular / cfg.robot.max_angular_speed, 0.0])
        assert specials > 240
    finally:
        env.close()
