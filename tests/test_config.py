"""One experiment config, one builder: the serial trainer and every service build the same parts,
a changed field reaches every service, services of one run must agree, the CLI refuses what it
cannot do, the imports point down, and curlnav shares an environment with proto-plus."""

from __future__ import annotations

import ast
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
    (["train", "--init-from", "runs/x"], "--init-from is for the serial trainer"),
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


def test_curlnav_and_proto_plus_install_and_import_side_by_side():
    code = ("import proto, curlnav.proto.messages as m; assert hasattr(proto, 'Message'), proto.__file__; "
            "assert m.Weights.KIND == 'weights'; print(proto.__file__)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd="/")
    assert result.returncode == 0, result.stderr
    assert "site-packages" in result.stdout


# -- layering: imports point down only ------------------------------------------------------------
LAYERS = {  # module prefix -> layer (0: bottom)
    "curlnav.sim": 0, "curlnav.worlds": 0, "curlnav.proto": 0, "curlnav.layout": 0, "curlnav.config": 0, "curlnav.files": 0,
    "curlnav.bus": 0, "curlnav.bus.transport": 0, "curlnav.bus.security": 0, "curlnav.bus.identity": 0,
    "curlnav.bus.mesh": 0, "curlnav.policy": 0,
    "curlnav.run": 0, "curlnav.run.record": 0, "curlnav.evaluation": 0, "curlnav.bench": 0,
    "curlnav.replay": 1, "curlnav.learner": 1, "curlnav.scheduler": 1, "curlnav.actor": 1, "curlnav.builder": 1,
    "curlnav.bus.service": 1, "curlnav.evaluation.protocol": 1, "curlnav.planners": 1,
    "curlnav.cli": 2, "curlnav.run.launch": 2, "curlnav.run.train": 2, "curlnav.run.serial": 2,
    "curlnav.run.pull": 2, "curlnav.run.evaluator": 2, "curlnav.run.supervise": 2, "curlnav.run.status": 2,
    "curlnav.run.options": 2, "curlnav.evaluation.plots": 2, "curlnav.evaluation.animation": 2,
    "curlnav.evaluation.compare": 2, "curlnav.evaluation.commands": 2, "curlnav.run.ablation": 2,
    "curlnav.run.experiment": 2,
    "curlnav.bench.transport": 2, "curlnav.bench.faults": 2, "curlnav.bench.draws": 2, "curlnav.bench.hosts": 2,
    "curlnav.bench.actor": 2, "curlnav.bench.chaos": 2,
    "curlnav.bench.learner": 2, "curlnav.bench.env": 2, "curlnav.bench.metrics": 2,
    "curlnav.ros2": 2,
}
FOLDERS = {"curlnav": "curlnav", "proto": "curlnav.proto", "replay": "curlnav.replay", "learner": "curlnav.learner",
           "actor": "curlnav.actor", "scheduler": "curlnav.scheduler"}


def layer_of(module: str) -> int | None:
    if module == "curlnav":
        return 0  # the package itself: a docstring and a version
    best = max((p for p in LAYERS if module == p or module.startswith(p + ".")), key=len, default=None)
    return None if best is None else LAYERS[best]


def project_modules():
    for folder, package in FOLDERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            yield ".".join([package, *parts]), path, path.name == "__init__.py"


def imports_of(module: str, path: Path, is_package: bool) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")[: len(module.split(".")) - node.level + (1 if is_package else 0)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            out.add(name)
    return {name for name in out if name.startswith("curlnav")}


def test_imports_point_down_only():
    upward = []
    for module, path, is_package in project_modules():
        own = layer_of(module)
        assert own is not None, f"{module} is in no layer"
        for target in imports_of(module, path, is_package):
            their = layer_of(target)
            if their is not None and their > own:
                upward.append(f"{module} (layer {own}) imports {target} (layer {their})")
            if module.startswith("curlnav.proto") and not target.startswith("curlnav.proto"):
                upward.append(f"{module}: the wire schemas import {target}")
            if module.startswith("curlnav.actor") and target.startswith("curlnav.learner") \
                    and target != "curlnav.learner.networks":
                upward.append(f"{module} imports learner internals ({target}), not the networks module")
    assert not upward, "\n".join(upward)


def test_no_import_circle_between_modules():
    """A circle (a imports b imports a, at import time or for type checking) makes a module
    impossible to read or move alone; `sim/env.py` <-> `sim/render.py` was one."""
    graph = {module: {t for t in imports_of(module, path, is_package)} for module, path, is_package in project_modules()}
    graph = {m: {t for t in targets if t in graph and t != m} for m, targets in graph.items()}
    state: dict[str, int] = {}
    circles = []

    def visit(module: str, stack: list[str]) -> None:
        state[module] = 1
        for target in sorted(graph[module]):
            if state.get(target) == 1:
                circles.append(" -> ".join(stack[stack.index(target):] + [target]))
            elif target not in state:
                visit(target, stack + [target])
        state[module] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    # a package's face importing its own submodules is not a circle a reader trips on
    circles = [c for c in circles if not any(c.startswith(p + " ->") for p in graph if c.split(" -> ")[1].startswith(p + "."))]
    assert not circles, "\n".join(circles)


def test_curlnav_keeps_at_most_twelve_modules_at_its_top_level_and_packages_declare_all():
    top = sorted(p.name for p in (ROOT / "curlnav").glob("*.py"))
    assert len(top) <= 12, top
    for folder in ["curlnav", *FOLDERS]:
        for init in (ROOT / folder).rglob("__init__.py"):
            tree = ast.parse(init.read_text())
            names = {t.id for node in tree.body if isinstance(node, ast.Assign) for t in node.targets
                     if isinstance(t, ast.Name)}
            if init.parent == ROOT / "curlnav":
                continue  # the namespace itself: a docstring and a version
            assert "__all__" in names, f"{init.relative_to(ROOT)} declares no __all__"
