"""The planner registry (``curlnav.nav.PLANNERS``): every planner is named in ``curlnav eval
--help``, every map-less one in ``curlnav ros2 run --help`` and runs in the ROS 2 node, every one
drives an episode; and a new planner is one module plus one registry line."""

from __future__ import annotations

import random
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from conftest import goal_of, step

from curlnav.cli import main
from curlnav.evaluation.protocol import evaluate, evaluation_config
from curlnav.nav import PLANNERS, Entry, agents_help, make_agent, make_planner, register, registry
from curlnav.sim import get_world

MAP_LESS = [name for name, p in PLANNERS.items() if p.map_less]


def help_of(capsys, monkeypatch, *command: str) -> str:
    """The help text of ``curlnav COMMAND --help``, unwrapped (so a name is never cut at its hyphen)."""
    monkeypatch.setenv("COLUMNS", "10000")
    with pytest.raises(SystemExit) as stopped:
        main([*command, "--help"])
    assert stopped.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("name", list(PLANNERS))
def test_every_planner_is_named_in_the_eval_help(name, capsys, monkeypatch):
    assert f"`{name}` ({PLANNERS[name].about}" in help_of(capsys, monkeypatch, "eval")


@pytest.mark.parametrize("name", list(PLANNERS))
def test_the_node_offers_the_map_less_planners_only(name, capsys, monkeypatch):
    shown = f"`{name}`" in help_of(capsys, monkeypatch, "ros2", "run")
    assert shown == PLANNERS[name].map_less


@pytest.mark.parametrize("name", list(PLANNERS))
def test_every_planner_drives_an_open_room_episode(name):
    cfg = evaluation_config()
    label, agent = make_agent(name, cfg, load_policy=lambda path: pytest.fail(f"{name} loaded as a policy"))
    assert label == name
    world = get_world("open-room")
    ends = []
    result = evaluate(agent, world, [world.pairs[0]], cfg, on_episode=lambda i, info: ends.append(info))
    assert result.success_rate == 1.0, f"{name} did not reach the goal of open-room's first pair"
    assert ends[0]["steps"] > 1


@pytest.mark.parametrize("name", MAP_LESS)
def test_every_map_less_planner_acts_in_the_ros2_node(name):
    from curlnav.ros2.commands import _agent
    from curlnav.ros2.node import PolicyNode

    agent, layout = _agent(name)
    node = PolicyNode(agent, layout)
    node.on_goal(goal_of(6.0, 0.0))
    commands = [step(node, 0.2 * k, (0.1 * k, 0.0, 0.0)) for k in range(10)]
    assert node.counts["policy_errors"] == 0 and node.counts["unsafe_commands"] == 0, dict(node.counts)
    assert all(c.state == "active" for c in commands)
    assert max(c.linear for c in commands) > 0.1, f"{name} in the node never drove toward a goal 6 m ahead"


def test_a_planner_that_needs_the_map_is_refused_by_the_node():
    from curlnav.ros2.commands import _agent

    with pytest.raises(ValueError, match="true map and pose"):
        _agent("oracle")


@pytest.mark.slow
@pytest.mark.net
def test_the_node_runs_a_planner_by_name_from_the_command_line():
    domain = random.randint(100, 230)  # each run its own DDS domain, as test_ros2's fixture does
    result = subprocess.run([sys.executable, "-m", "curlnav.cli", "ros2", "run", MAP_LESS[0], "--loopback",
                             "--duration-s", "1", "--domain-id", str(domain)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert f"curlnav ros2 run: {MAP_LESS[0]} on domain {domain}" in result.stderr


STRAIGHT = '''
import numpy as np


class Straight:
    """Turns toward the goal (read from the observation's newest goal frame), then drives at it."""

    label = "straight"

    def __init__(self, env_config):
        self.env_config = env_config

    def reset(self, world, pair):
        pass

    def act(self, observation, info):
        bearing = float(observation[-1])
        return np.array([1.0 if abs(bearing) < 0.3 else 0.0, float(np.clip(2.0 * bearing, -1.0, 1.0)), 0.0],
                        dtype=np.float32)
'''


def test_a_new_planner_is_one_module_and_one_registry_line(tmp_path, monkeypatch, capsys):
    (tmp_path / "straight_planner.py").write_text(textwrap.dedent(STRAIGHT))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(registry.ENTRIES, "controller", dict(registry.ENTRIES["controller"]))  # ends with the test
    register(Entry("controller", "straight", "straight_planner:Straight", "turns to the goal and drives at it", True))

    assert "`straight` (turns to the goal and drives at it)" in help_of(capsys, monkeypatch, "eval")
    assert "`straight` (turns to the goal and drives at it)" in help_of(capsys, monkeypatch, "ros2", "run")
    assert "`straight`" in agents_help(map_less_only=True)
    # it acts: an episode in the open room, and in the node
    cfg = evaluation_config()
    label, agent = make_agent("straight", cfg, load_policy=lambda path: pytest.fail("loaded as a policy"))
    assert label == "straight" and type(agent).__name__ == "Straight"
    world = get_world("open-room")
    ends = []
    evaluate(agent, world, [world.pairs[0]], cfg, on_episode=lambda i, info: ends.append(info))
    start = np.array(ends[0]["trajectory"][0])
    assert np.hypot(*(np.array(ends[0]["trajectory"][-1]) - start)) > 1.0, "the new planner did not move"
    from curlnav.ros2.commands import _agent
    from curlnav.ros2.node import PolicyNode

    node = PolicyNode(*_agent("straight"))
    node.on_goal(goal_of(6.0, 0.0))
    command = step(node, 0.0, (0.0, 0.0, 0.0))
    assert command.state == "active" and command.linear == pytest.approx(node.layout.max_linear_speed)


def test_a_name_is_registered_once_and_an_unknown_one_is_refused(monkeypatch):
    monkeypatch.setitem(registry.ENTRIES, "controller", dict(registry.ENTRIES["controller"]))
    with pytest.raises(ValueError, match="registered already"):
        register(Entry("controller", "dwa", "curlnav.nav.controllers.local:DynamicWindowPlanner", "again", True))
    with pytest.raises(ValueError, match="planners: tare-l, dwa, oracle"):
        make_planner("nope", evaluation_config())
    assert type(make_planner("planner", evaluation_config())).__name__ == "StaticMapPlanner"  # the old name
