"""Which part of a stack chose each command (issue 53): ``curlnav eval`` counts every trial's
control steps by chooser (``episodes.csv``'s ``control_steps``) and prints per agent
``control steps: network P%, ROLE Q%``; the network alone is 100 % network, a planner 100 % itself."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np

from curlnav.evaluation.protocol import evaluate, evaluation_config
from curlnav.nav import build_stack, parse_agent
from curlnav.nav.roles import NETWORK, ControlSteps, chooser
from curlnav.sim import NamoEnv, get_world

ROOT = Path(__file__).resolve().parent.parent
T_MAZE = str(ROOT / "scheduler/curricula/worlds/t-maze-0.yaml")
STRAIGHT = np.array([1.0, 0.0, 0.0], dtype=np.float32)


def straight_ahead(observation: np.ndarray) -> np.ndarray:
    """A controller that drives straight on whatever it sees: into the first wall."""
    return STRAIGHT.copy()


def layer(agent, role: str):
    while getattr(agent, "control_role", None) != role:
        agent = agent.policy
    return agent


def test_each_command_is_credited_to_the_part_of_the_stack_that_chose_it():
    """A controller that drives into a wall behind the shipped NAMO stack: every step whose command
    is not the controller's is credited to a helper, every other step to the network; the shield's
    count is its own count of replacements, the rescue's at most the steps it drove."""
    config = evaluation_config()
    _, agent = build_stack(parse_agent("policies/namo-robust"), config, lambda path: straight_ahead)
    world = get_world(T_MAZE)
    env = NamoEnv(world, config)
    try:
        obs, info = env.reset(seed=3, options={"world": world, "pair": world.pair("p4")})
        agent.reset(env.world, env.pair)
        steps = ControlSteps()
        for _ in range(300):
            command = agent.act(obs, info)
            role = steps.add(agent)
            assert (role == NETWORK) == bool(np.allclose(command[:2], STRAIGHT[:2])), (role, command)
            obs, _, terminated, truncated, info = env.step(command)
            if terminated or truncated:
                break
    finally:
        env.close()
    shield, rescue = layer(agent, "shield"), layer(agent, "rescue")
    assert steps.counts["shield"] == shield.interventions > 0
    assert 0 < steps.counts["rescue"] <= rescue.rescue_steps
    assert steps.counts[NETWORK] > 0 and steps.total == sum(steps.counts.values())
    assert chooser(straight_ahead) == NETWORK  # a bare policy: the network's


def test_eval_counts_and_prints_the_share_of_control_steps_per_agent(tmp_path):
    out = tmp_path / "eval"
    run = subprocess.run([sys.executable, "-m", "curlnav.cli", "eval", "policies/namo-robust+bare", "dwa",
                          "--world", T_MAZE, "--pair", "p4", "--episodes", "1", "--jobs", "1", "--out", str(out)],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    lines = {line.split(" on ")[0]: line for line in run.stdout.splitlines() if " on t-maze" in line}
    assert lines["policies/namo-robust+bare"].endswith("; control steps: network 100.0%")
    assert lines["dwa"].endswith("; control steps: dwa 100.0%")
    rows = list(csv.DictReader(open(out / "episodes.csv")))
    period = evaluation_config().control_period
    for row, role in zip(rows, (NETWORK, "dwa"), strict=True):
        counts = ControlSteps.parse(row["control_steps"]).counts
        assert list(counts) == [role] and counts[role] == round(float(row["time_s"]) / period)


def test_evaluate_gives_each_trial_its_control_steps():
    config = evaluation_config()
    _, agent = build_stack(parse_agent("policies/namo-robust+shield"), config, lambda path: straight_ahead)
    seen = []
    evaluate(agent, T_MAZE, [get_world(T_MAZE).pair("p4")], config, on_episode=lambda i, info: seen.append(info))
    (info,) = seen
    steps = info["control_steps"]
    assert steps.total == info["steps"] and steps.counts["shield"] > 0
    assert ControlSteps.parse(steps.text()).counts == steps.counts
    assert steps.line().startswith(f"control steps: network {steps.counts[NETWORK] / steps.total:.1%}, shield ")


def test_every_entry_is_credited_by_its_registry_name_however_its_stack_was_built():
    """A stack built by hand (``curlnav experiment``'s plan agent, the ROS 2 node's planner) is
    credited as ``build_stack``'s is: each entry's class names its own registry entry."""
    from curlnav.nav.registry import ENTRIES, POLICY_ENTRY

    named = {(role, name): getattr(entry.load(), "control_role", None)
             for role, entries in ENTRIES.items() for name, entry in entries.items() if name != POLICY_ENTRY}
    assert named and all(cls_role == name for (_, name), cls_role in named.items()), named
