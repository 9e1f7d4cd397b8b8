"""The guide "Bring your building" (docs/guide/your-building.md) runs as written: its commands, read
from the page, export a map, score the shipped policy on it, fine-tune it there with the distributed
trainer, score it again on the run's held-out pairs, and drive it as a ROS 2 node against the
simulator on the same map. Only the budget is shorter (``SHORTER``); every other word is the page's."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from conftest import ROOT, die_with_parent, output_of, stop_all, wait_for

GUIDE = ROOT / "docs" / "guide" / "your-building.md"
#: the budget of the guide's worked example, made short: (the page's words, the test's)
SHORTER = [
    ("--minutes 60", "--minutes 1 --pairs-held-out 3 --pairs-train 10"),
    ("--pairs 20", "--pairs 3"),
    ("--seeds 2", "--seeds 2 --pairs 2"),
]


def guide_commands() -> list[str]:
    """The commands of each ```bash block the page marks ``<!-- guide-commands -->``, in order."""
    text = GUIDE.read_text()
    blocks = re.findall(r"<!-- guide-commands -->\s*```bash\n(.*?)```", text, flags=re.S)
    return [line.strip() for block in blocks for line in block.splitlines() if line.strip()]


def shortened(command: str) -> list[str]:
    for page, test in SHORTER:
        command = command.replace(page, test)
    words = shlex.split(command)
    assert words[0] == "curlnav", command
    return [sys.executable, "-m", "curlnav.cli", *words[1:]]


def run(command: str, cwd: Path, timeout: float) -> str:
    done = subprocess.run(shortened(command), cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, f"{command}\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"
    return done.stdout + done.stderr


@pytest.mark.slow
@pytest.mark.net
def test_the_guide_takes_a_map_to_a_fine_tuned_policy_on_a_ros2_robot(tmp_path):
    commands = guide_commands()
    kinds = [c.split()[1] + (" " + c.split()[2] if c.split()[1] in ("worlds", "ros2") else "") for c in commands]
    assert kinds == ["worlds export-map", "eval", "train", "eval", "ros2 sim", "ros2 run"], kinds
    for name in ("policies", "configs"):  # the page runs from the repository's root
        (tmp_path / name).symlink_to(ROOT / name)
    export, before, train, after, sim, node = commands

    run(export, tmp_path, 120)
    assert (tmp_path / "maps" / "my-building.yaml").is_file() and (tmp_path / "maps" / "my-building.pgm").is_file()

    out = run(before, tmp_path, 600)
    for agent in ("policies/namo-robust+bare", "policies/namo-robust"):
        assert re.search(rf"^{re.escape(agent)} on my-building: success \d+% over 3 episodes", out, re.M), out[-1500:]

    out = run(train, tmp_path, 900)
    run_dir = tmp_path / "runs" / "my-building"
    pairs = yaml.safe_load((run_dir / "pairs.yaml").read_text())
    held_out = {(tuple(p["start"][:2]), tuple(p["goal"])) for p in pairs["held_out"]}
    trained = {(tuple(p["start"][:2]), tuple(p["goal"])) for p in pairs["train"]}
    assert len(held_out) == 3 and len(trained) == 10 and not held_out & trained
    summary = json.loads((run_dir / "summary.json").read_text())
    assert Path(summary["init_from"]["path"]).resolve() == ROOT / "policies" / "namo-robust"
    assert summary["before"]["episodes"] == 6  # each held-out pair with two ball placements
    shipped = json.loads((ROOT / "policies" / "namo-robust" / "metadata.json").read_text())
    tuned = json.loads((run_dir / "policy" / "metadata.json").read_text())
    assert tuned["stack"] == shipped["stack"], "the fine-tuned policy lost the stack it was shipped behind"
    assert tuned["training"]["d4pg"]["anchor_weight"] > 0  # the guide's recipe, from configs/fine-tune.yaml

    out = run(after, tmp_path, 600)
    for agent in ("policies/namo-robust+bare", "runs/my-building/policy+bare", "runs/my-building/policy"):
        assert re.search(rf"^{re.escape(agent)} on my-building: success \d+% over 4 episodes", out, re.M), out[-1500:]

    # the robot's command is the simulation's node command without --loopback
    assert node.replace(" --loopback", "") in GUIDE.read_text()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "ROS_DOMAIN_ID": str(100 + os.getpid() % 120)}
    logs = [open(tmp_path / f"{name}.log", "w+") for name in ("sim", "node")]
    procs = [subprocess.Popen(shortened(c), cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT, text=True,
                              preexec_fn=die_with_parent) for c, log in zip((sim, node), logs)]
    for proc, log in zip(procs, logs):
        proc.log = log  # for conftest's output_of
    try:
        wait_for("the node on its DDS domain", lambda: "on domain" in output_of(procs[1]), 90, procs)
        time.sleep(5)  # the node acts on the simulator's scans, at 5 Hz
    finally:
        stop_all(procs[::-1])
    said = output_of(procs[1])
    assert "loop latency over" in said and "'scans_refused'" not in said, said[-1500:]
    for log in logs:
        log.close()
