"""Training inside the stack (``helpers``, issue 53): an actor's network proposes, the helpers
(built as evaluation builds them) may take over, and the replay keeps the command that was
executed; each step a helper chose costs ``helpers.intervention_cost`` of reward (the shield's
``helpers.safety_cost`` where set); the helpers fade
out on their schedule; each episode's control steps by chooser reach the scheduler's ``/status``."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from curlnav.actor.vector import VectorEpisodeLoop, VectorNStepWriter
from curlnav.builder import D4PGBuilder
from curlnav.cli import main
from curlnav.config import ConfigError, ExperimentConfig, HelpersConfig
from curlnav.nav.roles import NETWORK
from curlnav.proto.codec import ProtoError
from curlnav.proto.messages import Assignment, AssignmentRequest, EpisodeReport
from curlnav.scheduler.curriculum import load_curriculum
from curlnav.scheduler.service import SchedulerCore

ROOT = Path(__file__).resolve().parent.parent
T_MAZE = str(ROOT / "scheduler/curricula/worlds/t-maze-0.yaml")
STRAIGHT = np.array([1.0, 0.0, 0.0], dtype=np.float32)


def straight_ahead(observations: np.ndarray) -> np.ndarray:
    """A behaviour policy that proposes full speed ahead in every environment: into the walls."""
    return np.tile(STRAIGHT, (len(observations), 1))


def run_loop(helpers: HelpersConfig, steps: int = 120, envs: int = 2):
    """``steps`` steps of ``envs`` T-maze environments behind ``helpers``, one-step transitions:
    (the transitions' actions and rewards per environment, the loop)."""
    experiment = dataclasses.replace(ExperimentConfig(), helpers=helpers)
    experiment = dataclasses.replace(experiment, curriculum=dataclasses.replace(experiment.curriculum, world=T_MAZE))
    builder = D4PGBuilder(experiment)
    writer = VectorNStepWriter(builder.layout, envs, n_step=1, discount=0.99)
    loop = VectorEpisodeLoop([builder.make_env() for _ in range(envs)], straight_ahead, writer,
                             helpers=builder.make_training_helpers(0, envs))
    actions, rewards = [[] for _ in range(envs)], [[] for _ in range(envs)]
    try:
        for k in range(envs):
            loop.begin(k, seed=10 + k, options={"world": T_MAZE, "pair": "p4"})
        for _ in range(steps):
            loop.step()
            for k in range(envs):
                out = writer[k].flush()
                actions[k].extend(out.action)
                rewards[k].extend(out.reward)
            for k in loop.waiting():
                loop.begin(k, seed=100 + k, options={"world": T_MAZE, "pair": "p4"})
    finally:
        loop.close()
    return [np.array(a) for a in actions], [np.array(r) for r in rewards], loop


@pytest.mark.parametrize("costs", [{"intervention_cost": 5.0}, {"intervention_cost": 0.5, "safety_cost": 5.0}],
                         ids=["intervention_cost", "safety_cost"])
def test_the_replay_keeps_the_executed_command_and_each_takeover_costs_its_price(costs):
    """The shield's takeovers cost ``intervention_cost``, or ``safety_cost`` where that is set."""
    free_actions, free_rewards, free = run_loop(HelpersConfig(stack="+shield", intervention_cost=0.0))
    actions, rewards, paid = run_loop(HelpersConfig(stack="+shield", **costs))
    taken_over = paid.helpers.steps.counts["shield"]
    assert taken_over > 0 and paid.helpers.steps.counts == free.helpers.steps.counts
    for k in range(2):
        replaced = ~np.all(np.isclose(actions[k], STRAIGHT), axis=1)  # the shield's command, not the proposal
        np.testing.assert_array_equal(actions[k], free_actions[k])  # the cost changes no command
        np.testing.assert_allclose(rewards[k] - free_rewards[k], np.where(replaced, -5.0, 0.0), atol=1e-4)
    assert sum(int((~np.all(np.isclose(a, STRAIGHT), axis=1)).sum()) for a in actions) == taken_over
    assert paid.helpers.steps.total == paid.steps


def test_helpers_faded_out_leave_every_step_to_the_network():
    _, _, loop = run_loop(HelpersConfig(stack="+rescue+shield", intervention_cost=1.0, share_start=0.0, share_end=0.0,
                                        fade_steps=10), steps=40)
    assert dict(loop.helpers.steps.counts) == {NETWORK: loop.steps} and loop.helpers.episodes_with == 0
    schedule = HelpersConfig(stack="+shield", share_start=1.0, share_end=0.2, fade_steps=1000)
    assert [schedule.share(s) for s in (0, 500, 1000, 5000)] == pytest.approx([1.0, 0.6, 0.2, 0.2])


@pytest.mark.parametrize(("setting", "words"), [
    ("helpers.stack=+rescue+track", "helpers.stack: +rescue+track: label-vote rewrite(s) what the network sees"),
    ("helpers.stack=rescue", "helpers.stack: rescue: no such stack file or policy folder; helpers are suffixes"),
    ("helpers.stack=inherit", "inherit takes the stack of the init_from artefact; set init_from"),
    ("helpers.share_end=1.5", "helpers.share_end must be a number in [0, 1]"),
    ("helpers.safety_cost=-2", "helpers.safety_cost must be a number in [0, inf) or none"),
])
def test_helpers_that_cannot_train_in_the_loop_are_refused_in_one_line(tmp_path, capsys, setting, words):
    run = tmp_path / "run"
    assert main(["train", "--serial", "--world", "open-room", "--set", setting, "--run-dir", str(run)]) == 2
    err = capsys.readouterr().err
    assert words in err and err.count("\n") == 1 and not run.exists()


def test_inherit_takes_the_recovery_and_safety_the_artefact_ships_and_refuses_one_that_ships_none():
    robust = ROOT / "policies" / "namo-robust"
    experiment = dataclasses.replace(ExperimentConfig(), init_from=str(robust), helpers=HelpersConfig(stack="inherit"))
    helpers = D4PGBuilder(experiment).make_training_helpers(0, 1)
    assert helpers.stack.recovery.to_dict()["rescue"]["stall_steps"] == 10 and helpers.stack.safety.entry == "shield"
    assert not helpers.stack.perception  # laser odometry rewrites what the network sees: not in the loop
    general = dataclasses.replace(experiment, init_from=str(ROOT / "policies" / "namo-general"))
    with pytest.raises(ValueError, match="namo-general ships no stack"):
        D4PGBuilder(general).make_training_helpers(0, 1)


def test_a_network_trained_from_scratch_takes_its_helpers_from_a_stack_file_or_a_policy_folder(tmp_path):
    """``helpers.stack: FILE.yaml`` (``curlnav stack show AGENT --out``) or a policy folder: its
    recovery and safety entries, settings and all, train in the loop without ``init_from``."""
    robust = ROOT / "policies" / "namo-robust"
    assert main(["stack", "show", str(robust), "--out", str(tmp_path / "helpers.yaml")]) == 0
    for spec in (str(tmp_path / "helpers.yaml"), str(robust)):
        experiment = dataclasses.replace(ExperimentConfig(), helpers=HelpersConfig(stack=spec))
        stack = D4PGBuilder(experiment).make_training_helpers(0, 1).stack
        assert stack.recovery.to_dict()["rescue"]["stall_steps"] == 10 and stack.safety.entry == "shield"
        assert not stack.perception
    general = dataclasses.replace(ExperimentConfig(), helpers=HelpersConfig(stack=str(ROOT / "policies" / "namo-general")))
    with pytest.raises(ValueError, match="helpers.stack: .*namo-general ships no stack"):
        D4PGBuilder(general).make_training_helpers(0, 1)


def test_the_scheduler_shows_the_share_of_control_steps_and_counts_a_malformed_one(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("name: c\nstages:\n  - name: S1\n    worlds: [open-room]\n")
    core = SchedulerCore(load_curriculum(path))
    core.actor_joined("a1")
    Assignment.decode(core.assign(AssignmentRequest("a1").encode()))
    report = EpisodeReport("a1", "open-room", "", True, 200.0, 0, 0, 100, 1, 0, {"network": 70, "rescue": 30})
    assert EpisodeReport.decode(report.encode()) == report
    core.report(report.encode())
    core.report(EpisodeReport("a1", "open-room", "", False, -5.0, 1, 0, 100, 1, 0).encode())  # no helpers: the network's
    bad = dataclasses.replace(report, control_steps={"network": -1})
    with pytest.raises(ProtoError):
        bad.encode()
    import msgpack

    raw = msgpack.unpackb(report.encode())
    for wrong in ({"network": "many"}, {"network": 70, "rescue": 31}, {"network": 70, "res\ncue": 30}):
        raw["control_steps"] = wrong  # not a count, not the episode's steps, not a role's name
        assert not core.report(msgpack.packb(raw))
    status = core.status()
    assert status["control_steps_last_100"] == {"network": 0.85, "rescue": 0.15}
    assert status["episodes"] == 2 and status["rejected"] == {"range": 3}
    from curlnav.run.status import format_status

    assert "control steps, last 100 episodes: network 85%, rescue 15%" in format_status(status).splitlines()


def test_a_restarted_actor_goes_on_with_the_helpers_fade_where_it_was(tmp_path):
    from curlnav.actor.service import HELPERS_FILE, ActorServiceConfig
    from curlnav.bus.service import Deployment

    experiment = dataclasses.replace(ExperimentConfig(), helpers=HelpersConfig(
        stack="+shield", share_start=1.0, share_end=0.0, fade_steps=10_000))
    experiment = dataclasses.replace(experiment, curriculum=dataclasses.replace(experiment.curriculum, world=T_MAZE))
    cfg = ActorServiceConfig(actor_id="actor-0", deployment=Deployment(data_dir=str(tmp_path)), envs=1)
    (tmp_path / HELPERS_FILE).write_text('{"env_steps": 7500}\n')
    service = D4PGBuilder(experiment).make_actor_service(cfg)
    try:
        assert service.core.loop.steps == 7500 and experiment.helpers.share(service.core.loop.steps) == 0.25
        service.core.loop.steps = 9000
        service._save_helpers(force=True)
        assert (tmp_path / HELPERS_FILE).read_text() == '{"env_steps": 9000}\n'
    finally:
        service.core.loop.close()


def test_a_metrics_file_of_an_older_run_keeps_its_rows_when_columns_are_added(tmp_path):
    from curlnav.run.record import TRAIN_FIELDS, CsvLog, read_csv

    old = TRAIN_FIELDS[:-1]  # before network_control_share_100
    path = tmp_path / "metrics.csv"
    path.write_text(",".join(old) + "\n" + ",".join("1" for _ in old) + "\n")
    log = CsvLog(path, TRAIN_FIELDS)
    log.write({"wall_s": 2.0, "network_control_share_100": 0.5})
    log.close()
    rows = read_csv(path)
    assert [r["wall_s"] for r in rows] == ["1", "2"] and [r["network_control_share_100"] for r in rows] == ["", "0.5"]
    assert not path.with_suffix(".csv.old").exists()


def test_a_config_with_helpers_has_a_new_hash_and_one_without_keeps_its_own():
    from curlnav.config import config_hash

    plain = ExperimentConfig()
    assert config_hash(dataclasses.replace(plain, helpers=HelpersConfig())) == config_hash(plain)
    assert config_hash(dataclasses.replace(plain, helpers=HelpersConfig(stack="+shield"))) != config_hash(plain)
    with pytest.raises(ConfigError):
        HelpersConfig(fade_steps=-1)
    with pytest.raises(ConfigError, match="fade_steps is 0: give the steps to fade over"):
        HelpersConfig(stack="+shield", share_end=0.2)
