"""One experiment config, one builder: the serial trainer and every service build the same parts,
a changed field reaches every service, services of one run must agree, the CLI refuses what it
cannot do, the imports point down, and curlnav shares an environment with proto-plus."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from curlnav.bus.service import ConfigMismatch, check_agreement
from curlnav.cli import build_parser, main
from curlnav.config import (
    PRESETS,
    ConfigError,
    ExperimentConfig,
    config_hash,
    config_to_dict,
    load_config,
    resolve_config,
    service_config_hash,
)
from curlnav.proto.messages import RunConfig
from curlnav.run.launch import build_service, free_port
from curlnav.run.serial import SerialRunConfig, SerialTrainer

ROOT = Path(__file__).resolve().parent.parent


def serve_args(role: str, tmp_path: Path, *more: str):
    return build_parser().parse_args(["serve", role, "--data-dir", str(tmp_path / "svc"), *more])


def limiter_settings(table) -> tuple:
    limiter = table.rate_limiter
    return (table.max_size, table.sampler, table.priority_exponent, limiter.samples_per_insert,
            limiter.min_size_to_sample, limiter.error_buffer)


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_serial_and_distributed_modes_build_the_same_parts_from_one_config(preset, tmp_path, monkeypatch):
    monkeypatch.delenv("CURLNAV_PRESET", raising=False)
    experiment = ExperimentConfig.preset(preset)
    serial = SerialTrainer(tmp_path / "serial", experiment, SerialRunConfig(progress=False))
    replay = build_service(serve_args("replay", tmp_path, "--preset", preset))
    learner = build_service(serve_args("learner", tmp_path, "--preset", preset))
    actor = build_service(serve_args("actor", tmp_path, "--preset", preset, "--actor-index", "0"))
    try:
        assert limiter_settings(replay.table) == limiter_settings(serial.table)
        assert learner.state.config == serial.state.config == experiment.d4pg
        shapes = {k: tuple(v.shape) for k, v in serial.state.critic.state_dict().items()}
        assert {k: tuple(v.shape) for k, v in learner.state.critic.state_dict().items()} == shapes
        behaviour = actor.core.policy
        assert (behaviour.sigma, behaviour.warmup_steps) == (serial.policy.sigma, serial.policy.warmup_steps)
        assert behaviour.sigma == experiment.exploration.sigma_ladder[0]
        for writer in (actor.core.loop.writer, serial.loop.writer):
            assert (writer.n_step, writer.discount) == (experiment.d4pg.n_step, experiment.d4pg.discount)
        assert actor.core.loop.env.config == serial.loop.env.config == experiment.env
        for service in (replay, learner, actor):
            assert service.experiment == experiment
    finally:
        serial.loop.close()
        actor.core.loop.close()


def test_a_changed_field_reaches_every_service(tmp_path, monkeypatch):
    monkeypatch.setenv("CURLNAV_D4PG__N_STEP", "3")  # a CURLNAV_* variable maps to the same field
    changes = ["--set", "d4pg.batch_size=64", "--set", "replay.min_size=640", "--set", "exploration.sigma_ladder=[0.9]",
               "--set", "actor.envs_per_process=2", "--world", "door-corridor"]
    services = {role: build_service(serve_args(role, tmp_path, *changes, *(["--actor-index", "5"] if role == "actor"
                                                                            else [])))
                for role in ("replay", "learner", "scheduler", "actor")}
    expected = resolve_config(overrides=["d4pg.batch_size=64", "replay.min_size=640", "exploration.sigma_ladder=[0.9]",
                                         "curriculum.world=door-corridor", "d4pg.n_step=3", "actor.envs_per_process=2"],
                             environ={})
    try:
        assert {config_hash(s.experiment) for s in services.values()} == {config_hash(expected)}
        assert services["replay"].table.rate_limiter.min_size_to_sample == 640
        assert services["learner"].state.config.batch_size == 64 and services["learner"].state.config.n_step == 3
        assert services["actor"].core.policy.sigma == 0.9 and services["actor"].core.loop.writer.n_step == 3
        assert services["actor"].core.default_world == "door-corridor"
        assert services["actor"].core.loop.size == 2 and services["actor"].cfg.envs == 2
        assert services["scheduler"].core.curriculum.stages[0].worlds == ("door-corridor",)
    finally:
        services["actor"].core.loop.close()


def test_a_service_with_another_config_is_refused_naming_the_field():
    ours = ExperimentConfig()
    theirs = resolve_config(overrides=["d4pg.batch_size=512"], environ={})
    same = RunConfig("learner", "0", service_config_hash(ours), json.dumps(config_to_dict(ours)))
    check_agreement(ours, [same])
    longer = resolve_config(overrides=["budget.minutes=60"], environ={})  # the launcher's own section
    check_agreement(ours, [RunConfig("learner", "0", service_config_hash(longer), json.dumps(config_to_dict(longer)))])
    batched = resolve_config(overrides=["actor.envs_per_process=8"], environ={})  # each actor's own choice
    check_agreement(ours, [RunConfig("actor", "a1", service_config_hash(batched), json.dumps(config_to_dict(batched)))])
    other = RunConfig("learner", "0", service_config_hash(theirs), json.dumps(config_to_dict(theirs)))
    with pytest.raises(ConfigMismatch) as info:
        check_agreement(ours, [same, other])
    message = str(info.value)
    assert "d4pg.batch_size 256 vs 512" in message and "learner" in message and "\n" not in message


@pytest.mark.net
@pytest.mark.slow
def test_a_joining_service_with_another_config_exits_2_with_one_line(tmp_path):
    """Real processes: a router and a replay on one config; a learner on another refuses to join."""
    port = free_port()
    router = f"tcp/127.0.0.1:{port}"
    common = ["--run", "agree", "--router", router, "--data-dir", str(tmp_path), "--router-timeout-s", "30"]
    procs = [subprocess.Popen([sys.executable, "-m", "curlnav.cli", "serve", "router", "--listen", router, *common],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        procs.append(subprocess.Popen([sys.executable, "-m", "curlnav.cli", "serve", "replay", *common],
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
        deadline = time.monotonic() + 120
        while not (tmp_path / "replay" / "http_port").exists():
            assert time.monotonic() < deadline, "the replay never came up"
            assert procs[1].poll() is None, procs[1].stdout.read()[-2000:]
            time.sleep(0.2)
        joined = subprocess.run([sys.executable, "-m", "curlnav.cli", "serve", "learner", *common,
                                 "--set", "d4pg.batch_size=128"], capture_output=True, text=True, timeout=180)
        assert joined.returncode == 2, joined.stderr[-2000:]
        error = [line for line in joined.stderr.splitlines() if line.startswith("curlnav: error:")]
        assert len(error) == 1 and "d4pg.batch_size 128 vs 256" in error[0] and "replay" in error[0], joined.stderr
    finally:
        for proc in procs:
            proc.terminate()
        for proc in procs:
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@pytest.mark.parametrize("text, message", [
    ("d4pg: {batch: 3}\n", "unknown config key d4pg.batch"),
    ("replay: {min_size: -5}\n", "replay.min_size must be a positive number"),
    ("d4pg: {hidden: [64, x]}\n", r"d4pg.hidden\[1\] must be an integer"),
    ("d4pg: [oops\n", "not valid YAML"),
    ("preset: huge\n", "unknown preset 'huge'"),
])
def test_a_broken_config_file_is_one_line_naming_file_and_field(tmp_path, text, message):
    path = tmp_path / "run.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as info:
        load_config(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_config_show_prints_the_resolved_config_and_a_file_round_trips(tmp_path, capsys):
    assert main(["config", "show", "--preset", "paper", "--set", "replay.prioritized=true"]) == 0
    text = capsys.readouterr().out
    (tmp_path / "shown.yaml").write_text(text)
    loaded = load_config(tmp_path / "shown.yaml")
    assert loaded.d4pg.encoder == "conv" and loaded.replay.prioritized and loaded.replay.min_size == 10_000
    assert f"# experiment config hash {config_hash(loaded)}" in text


@pytest.mark.parametrize("argv, message", [
    (["train", "--serial", "--actors", "3"], "--actors is for the distributed trainer"),
    (["train", "--init-from", "runs/x"], "init_from runs/x: no such file or folder"),
    (["train", "--actors", "0"], "--actors must be at least 1"),
    (["train", "--set", "d4pg.batch_size=0"], "d4pg.batch_size must be a positive number"),
    (["train", "--set", "replay.min_size=100"], "must be at least d4pg.batch_size"),
    (["train", "--resume"], "nothing to resume"),
    (["train", "--world", "namo-office:300"], "namo-office seed 300 is held out for evaluation"),
    (["train", "--serial", "--world", "namo-office:300"], "namo-office seed 300 is held out for evaluation"),
    (["train", "--serial", "--curriculum", str(Path(__file__).parents[1] / "scheduler" / "curricula" / "s1+s2-eval.yaml"),
      "--eval-episodes", "20"], "stage S1's advance (source: evaluation, window 8) can never fire"),
])
def test_train_refuses_what_it_cannot_do_with_exit_2(tmp_path, capsys, argv, message):
    assert main(argv + ["--run-dir", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_train_refuses_to_start_over_a_saved_run_without_resume(tmp_path, capsys):
    (tmp_path / "run" / "checkpoints").mkdir(parents=True)
    (tmp_path / "run" / "checkpoints" / "latest.safetensors").write_bytes(b"x")
    assert main(["train", "--serial", "--run-dir", str(tmp_path / "run")]) == 2
    assert "add --resume" in capsys.readouterr().err


@pytest.mark.slow
def test_curlnav_and_proto_plus_install_and_import_side_by_side():
    code = ("import proto, curlnav.proto.messages as m; assert hasattr(proto, 'Message'), proto.__file__; "
            "assert m.Weights.KIND == 'weights'; print(proto.__file__)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd="/")
    assert result.returncode == 0, result.stderr
    assert "site-packages" in result.stdout


# -- layering: tests/test_layers.py ---------------------------------------------------------------
def test_curlnav_keeps_at_most_twelve_modules_at_its_top_level():
    top = sorted(p.name for p in (ROOT / "curlnav").glob("*.py"))
    assert len(top) <= 12, top


def test_every_shipped_experiment_config_loads_with_the_curriculum_and_robot_it_names():
    """``configs/*.yaml`` are the documented recipes (barn-jackal, namo-robust and its ablation arm,
    fine-tune): each must load, name a curriculum file that exists (fine-tune, for a user's own map,
    names none), and keep its robot and senses."""
    from pathlib import Path

    from curlnav.config import load_config

    root = Path(__file__).resolve().parents[1]
    paths = sorted((root / "configs").glob("*.yaml"))
    assert len(paths) >= 4
    for path in paths:
        config = load_config(path)
        if path.name == "fine-tune.yaml":  # the recipe for a user's map (--world MAP.yaml): no curriculum
            assert not config.curriculum.file and config.d4pg.anchor_weight > 0, path.name
            continue
        assert (root / config.curriculum.file).is_file(), path.name
    senses_only = load_config(root / "configs" / "namo-robust-senses-only.yaml")
    robust = load_config(root / "configs" / "namo-robust.yaml")
    assert senses_only.env.sensor_noise == robust.env.sensor_noise  # the ablation changes the worlds only
    assert senses_only.curriculum.file != robust.curriculum.file
