"""A navigation stack is configuration: ``curlnav stack show`` prints every role of any agent, a
stack file runs in ``curlnav eval --stack``, meaningless spellings are refused in one line, and one
function (``curlnav.nav.build.build_stack``) builds the stack of every entry point."""

from __future__ import annotations

import csv
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from curlnav.evaluation.protocol import evaluation_config
from curlnav.nav import NavStack, build_stack, load_stack, make_agent, parse_agent
from curlnav.nav.registry import ENTRIES

ROOT = Path(__file__).resolve().parent.parent
ROBUST = "policies/namo-robust"
JACKAL = "policies/barn-jackal"


def curlnav(*args: str, cwd: Path = ROOT, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "curlnav.cli", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout)


def test_stack_show_prints_every_role_of_the_shipped_policies_with_every_setting():
    for artefact, rescue, perception in ((ROBUST, {"stall_steps": 10, "max_steps": 50}, ["laser-odometry"]),
                                         (JACKAL, {"reverse": True}, [])):
        shown = curlnav("stack", "show", artefact)
        assert shown.returncode == 0, shown.stderr
        stack = yaml.safe_load(shown.stdout)
        assert stack["label"] == artefact
        assert stack["controller"] == {"entry": "policy", "path": artefact}
        assert stack["global_planner"] is None
        assert stack["recovery"]["entry"] == "rescue"
        assert {k: stack["recovery"]["rescue"][k] for k in rescue} == rescue
        assert stack["safety"]["entry"] == "shield"
        assert [p["entry"] for p in stack["perception"]] == perception
        for role in ("recovery", "safety", *(["perception"] if perception else [])):
            for choice in (stack[role] if role == "perception" else [stack[role]]):
                entry = ENTRIES[role][choice["entry"]]
                for section, cls in entry.config_classes().items():  # every setting, resolved
                    assert set(choice[section]) == {f.name for f in dataclasses.fields(cls)}, (role, section)


def test_a_stack_file_gives_the_same_trials_as_the_artefact_it_was_shown_from(tmp_path):
    robust = tmp_path / "robust.yaml"
    assert curlnav("stack", "show", ROBUST, "--out", str(robust)).returncode == 0
    common = ["--world", "namo-office:90", "--pairs", "1", "--jobs", "1"]
    named = curlnav("eval", ROBUST, *common, "--out", str(tmp_path / "named"))
    filed = curlnav("eval", "--stack", str(robust), *common, "--out", str(tmp_path / "filed"))
    assert named.returncode == 0 and filed.returncode == 0, named.stderr + filed.stderr
    rows = [list(csv.DictReader(open(tmp_path / out / "episodes.csv"))) for out in ("named", "filed")]
    assert rows[0] and rows[0] == rows[1]  # the stack file's label is the artefact's: the rows are the same
    # a setting changed in the file reaches the role it belongs to
    data = yaml.safe_load(robust.read_text())
    data["recovery"]["rescue"]["stall_steps"] = 7
    robust.write_text(yaml.safe_dump(data))
    _, agent = build_stack(load_stack(robust), evaluation_config(), lambda path: (lambda obs: np.zeros(3)))
    assert agent.policy.policy.config.stall_steps == 7


@pytest.mark.parametrize(("spec", "words"), [
    ("dwa+bare", "dwa is a planner: name it alone"),
    (f"{JACKAL}+shield+shield", "+shield is named 2 times"),
    (f"{JACKAL}+sheild", "unknown suffix '+sheild'; suffixes: +global-plan"),
    ("dwa+sheild", "unknown suffix '+sheild'"),
    (f"{JACKAL}+bare+shield", f"takes no other suffix; name the helpers you want instead ({JACKAL}+shield)"),
    (f"{JACKAL}+bare+global-plan", f"instead ({JACKAL}+global-plan)"),
    (f"{JACKAL}+shield+rescue", "suffixes stack in the order POLICY[+global-plan|+scan-plan]"),
    ("oracle+shield", "oracle plans on the true map"),
])
def test_a_meaningless_agent_is_refused_naming_the_valid_form(spec, words):
    with pytest.raises(ValueError, match=None) as refused:
        parse_agent(spec)
    assert words in str(refused.value) and "\n" not in str(refused.value)


@pytest.mark.parametrize("spec", ["dwa+bare", f"{JACKAL}+shield+shield", "oracel"])
def test_eval_refuses_a_meaningless_agent_in_one_line(spec):
    """Before any world is built or any policy loaded."""
    done = curlnav("eval", spec, "--world", "open-room", "--pairs", "1", timeout=120)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("curlnav: error: ") and spec in lines[0]
    assert "oracel" not in spec or "planners: tare-l, dwa, oracle" in lines[0]


def test_the_spellings_build_the_stacks_they_always_did():
    """Labels and wrappers as the agent arguments have always made them (the results' rows depend on both)."""
    cfg = evaluation_config()
    policy = lambda obs: np.zeros(3, dtype=np.float32)  # noqa: E731
    load = lambda path: policy  # noqa: E731
    label, agent = make_agent(ROBUST, cfg, load)
    assert label == ROBUST
    assert [type(a).__name__ for a in (agent, agent.policy, agent.policy.policy)] == \
        ["ScanMatchedPolicy", "ShieldedPolicy", "RescuedPolicy"]
    assert agent.policy.policy.policy is policy and agent.policy.policy.config.stall_steps == 10
    label, agent = make_agent(ROBUST, cfg, load, global_plan=True)  # the shipped stack behind a global plan
    assert label == f"{ROBUST}+global-plan" and agent.policy.static_map
    assert type(agent.policy.policy.fallback).__name__ == "PlanTracker"
    assert make_agent(f"{ROBUST}+global-plan", cfg, load)[0] == f"{ROBUST} + global plan"
    assert make_agent(f"{ROBUST}+bare", cfg, load) == (f"{ROBUST}+bare", policy)
    assert make_agent(f"{ROBUST}+bare", cfg, load, global_plan=True)[0] == f"{ROBUST}+bare+global-plan"
    label, agent = make_agent("dwa+scan-plan+rescue", cfg, load)
    assert label == "dwa+scan-plan+rescue" and type(agent.policy).__name__ == "ScanMapPlanAgent"
    assert make_agent("planner", cfg, load)[0] == "oracle"


def test_an_artefacts_stack_is_read_from_its_metadata_and_a_broken_one_is_refused_by_name(tmp_path):
    artefact = tmp_path / "policy"
    artefact.mkdir()
    meta = artefact / "metadata.json"
    meta.write_text(json.dumps({"stack": {"safety": {"entry": "shield", "shield": {"margin_m": 0.1}}}}))
    stack = parse_agent(str(artefact))
    assert stack.safety.config("shield").margin_m == 0.1 and stack.recovery is None
    for bad, words in (({"safety": {"entry": "sheild"}}, "no entry 'sheild'; entries: shield"),
                       ({"safety": {"entry": "shield", "shield": {"margin": 1}}}, "no setting 'margin'"),
                       ({"safety": {"entry": "shield", "shield": {"margin_m": "wide"}}}, "must be a finite number"),
                       ({"recovery": {"entry": "rescue", "rescue": {"stall_steps": 0}}}, "stall_steps"),
                       ({"perception": [{"entry": "laser-odometry"}, {"entry": "label-vote"}]}, "in the order"),
                       ({"controller": "dwa"}, "stack must be a mapping of the roles round the network")):
        meta.write_text(json.dumps({"stack": bad}))
        with pytest.raises(ValueError) as refused:
            parse_agent(str(artefact))
        assert words in str(refused.value) and str(meta) in str(refused.value), bad


def test_a_broken_stack_file_is_refused_in_one_line_naming_the_file(tmp_path):
    broken = tmp_path / "broken.yaml"
    for text, words in (("controller: {entry: dwa}\nsafty: {entry: shield}\n", "no key 'safty'"),
                        ("safety: {entry: shield}\n", "controller is missing"),
                        ("controller: {entry: policy}\n", "a policy needs the path"),
                        ("controller: {entry: oracle}\nsafety: shield\n", "oracle plans on the true map")):
        broken.write_text(text)
        done = curlnav("eval", "--stack", str(broken), "--world", "open-room", "--pairs", "1", timeout=120)
        assert done.returncode == 2, text
        assert len(done.stderr.strip().splitlines()) == 1 and words in done.stderr and str(broken) in done.stderr, \
            done.stderr


def test_one_function_builds_every_stack(tmp_path, monkeypatch):
    """``curlnav eval``, ``policy run``, ``ros2 run`` (its node's stack) and the actors all build
    through ``curlnav.nav.build.build_stack``."""
    import curlnav.nav.build as build
    from curlnav.builder import D4PGBuilder
    from curlnav.cli import main
    from curlnav.config import ExperimentConfig
    from curlnav.ros2.commands import deployed, node_stack
    from curlnav.ros2.node import ScanLayout

    built: list[NavStack] = []
    real = build.build_stack

    def recording(stack, *args, **kwargs):
        built.append(stack)
        return real(stack, *args, **kwargs)

    monkeypatch.setattr(build, "build_stack", recording)
    assert main(["eval", "dwa+shield", "--world", "open-room", "--pairs", "1", "--jobs", "1"]) == 0
    assert [s.label for s in built] == ["dwa+shield"]
    assert main(["policy", "run", ROBUST, "--world", "open-room", "--pair", "0", "--out", str(tmp_path / "run")]) == 0
    assert built[-1].shorthand == f"{ROBUST}+rescue+shield+scan-match"
    args = dataclasses.make_dataclass("Args", [])()
    for flag in ("scan_plan", "rescue", "track", "scan_match", "bare", "global_plan"):
        setattr(args, flag, False)
    args.agent, args.shield = "dwa", True
    stack, follow_plan = node_stack(args)
    deployed(lambda obs: np.zeros(3), ScanLayout(), "husky", stack)
    assert built[-1].shorthand == "dwa+shield" and not follow_plan
    builder = D4PGBuilder(ExperimentConfig())
    loop = builder.make_actor_loop(0, builder.make_behaviour_policy(), envs=1)
    loop.close()
    assert built[-1].label == "behaviour policy" and len(built) == 4


def test_a_shipped_stack_behind_a_global_plan_is_named_whole_in_the_first_line_and_the_results():
    from curlnav.nav import deploy_notice

    stack = parse_agent(ROBUST, global_plan=True)
    line = deploy_notice(ROBUST, f"{ROBUST}+bare: the network alone", global_plan=True)
    assert f"driven as its artefact ships it, {ROBUST}+global-plan+rescue+shield+scan-match" in line
    assert stack.shorthand == f"{ROBUST}+global-plan+rescue+shield+scan-match"
    assert stack.label == f"{ROBUST}+global-plan"  # the results' name says the plan too
