"""What a person sees from the command line: no PyBullet banner, ``--version``, defaults in
``--help``, one-line errors for their mistakes, ``policy run --gif``, ``curlnav status``; and
saved replay files that grow with their content, not with the table's capacity."""

from __future__ import annotations

import hashlib
import http.server
import importlib.metadata
import json
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, closed_port
from conftest import run_curlnav as curlnav

from curlnav.cli import build_parser
from curlnav.layout import ObservationLayout
from curlnav.replay import NStepWriter, ReplayTable
from curlnav.sim import EnvConfig

REPO = Path(__file__).resolve().parent.parent
BANNER = "pybullet build time"


# -- banner, version, help -------------------------------------------------------------------------
@pytest.mark.slow
def test_version_prints_the_package_version_and_no_banner():
    result = curlnav("--version")
    assert result.returncode == 0, result.stderr
    assert result.stdout == f"curlnav {importlib.metadata.version('curlnav')}\n"
    assert BANNER not in result.stdout + result.stderr


@pytest.mark.slow
def test_a_command_that_builds_a_pybullet_scene_prints_no_banner(tmp_path):
    result = curlnav("rollout", "--world", "open-room", "--steps", "5", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr[-2000:]
    assert "picture:" in result.stdout
    assert BANNER not in result.stdout + result.stderr
    assert result.stderr == ""


@pytest.mark.parametrize("command, shown", [
    (["eval"], ["(default: 50)", "(default: open-room)"]),
    (["policy", "run"], ["(default: runs/policy-run)", "(default: 0)"]),
    (["worlds", "generate"], ["(default: worlds)"]),
    (["bench", "learner"], ["(default: default,paper)", "(default: 256)"]),
])
def test_sub_command_help_shows_the_defaults(capsys, monkeypatch, command, shown):
    monkeypatch.setenv("COLUMNS", "200")  # no line breaks inside "open-room"
    with pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args([*command, "--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    for default in shown:
        assert default in text
    assert "(default: None)" not in text and "(default: False)" not in text


@pytest.mark.slow
def test_eval_help_from_the_command_line_shows_the_episode_default():
    result = curlnav("eval", "--help")
    assert result.returncode == 0
    assert "(default: 50)" in " ".join(result.stdout.split())


# -- one-line errors for user mistakes ----------------------------------------------------------------
@pytest.mark.slow
def test_eval_of_a_missing_folder(tmp_path):
    missing = tmp_path / "no-such-policy"
    assert_one_line_error(curlnav("eval", str(missing)), str(missing), "expected a policy artefact folder")


@pytest.mark.slow
def test_eval_of_a_text_file_named_safetensors(tmp_path):
    fake = tmp_path / "x.safetensors"
    fake.write_text("not a checkpoint\n")
    assert_one_line_error(curlnav("eval", str(fake)), str(fake), "not a safetensors file")


@pytest.mark.slow
def test_eval_of_a_safetensors_file_that_is_no_curlnav_checkpoint(tmp_path):
    import torch
    from safetensors.torch import save_file

    other = tmp_path / "other.safetensors"
    save_file({"weight": torch.zeros(3)}, str(other))
    assert_one_line_error(curlnav("eval", str(other)), str(other), "checkpoint")


@pytest.mark.slow
def test_eval_of_a_folder_with_garbage_metadata(tmp_path, artefact):
    folder = tmp_path / "policy"
    folder.mkdir()
    for name in ("actor.onnx", "policy.safetensors"):
        (folder / name).write_bytes((artefact / name).read_bytes())
    (folder / "metadata.json").write_text("{garbage")
    assert_one_line_error(curlnav("eval", str(folder)), str(folder / "metadata.json"), "not valid JSON")


@pytest.mark.slow
def test_eval_of_a_folder_with_a_corrupt_onnx_model(tmp_path, artefact):
    folder = tmp_path / "policy"
    folder.mkdir()
    (folder / "policy.safetensors").write_bytes((artefact / "policy.safetensors").read_bytes())
    (folder / "actor.onnx").write_bytes(b"this is not an onnx model")
    meta = json.loads((artefact / "metadata.json").read_text())
    meta["files"]["actor.onnx"] = hashlib.sha256(b"this is not an onnx model").hexdigest()  # checksum agrees
    (folder / "metadata.json").write_text(json.dumps(meta))
    assert_one_line_error(curlnav("eval", str(folder)), str(folder / "actor.onnx"), "not a loadable ONNX model")


@pytest.mark.slow
def test_policy_run_on_a_file_instead_of_a_folder(tmp_path, artefact):
    assert_one_line_error(curlnav("policy", "run", str(artefact / "actor.onnx"), "--out", str(tmp_path)),
                          str(artefact / "actor.onnx"), "not a folder")


@pytest.mark.slow
def test_policy_run_on_a_missing_folder(tmp_path):
    missing = tmp_path / "gone"
    assert_one_line_error(curlnav("policy", "run", str(missing), "--out", str(tmp_path)), str(missing),
                          "no such folder")


@pytest.mark.slow
def test_pull_from_an_unreachable_learner(tmp_path):
    assert_one_line_error(curlnav("pull", "--from", "http://127.0.0.1:1", "--out", str(tmp_path / "p")),
                          "cannot reach http://127.0.0.1:1")
    assert not (tmp_path / "p").exists()


# -- policy run --gif ------------------------------------------------------------------------------------
@pytest.mark.slow
def test_policy_run_with_gif_writes_an_animation_beside_the_picture(tmp_path, artefact):
    from PIL import Image

    result = curlnav("policy", "run", str(artefact), "--world", "open-room", "--pair", "across", "--gif",
                     "--out", str(tmp_path), timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    lines = dict(line.split(": ", 1) for line in result.stdout.splitlines() if line.startswith(("picture", "animation")))
    picture, animation = Path(lines["picture"]), Path(lines["animation"])
    assert picture.exists() and animation == picture.with_suffix(".gif")
    with Image.open(animation) as gif:
        assert gif.format == "GIF"
        assert 1 < gif.n_frames <= 150
    assert BANNER not in result.stdout + result.stderr


@pytest.mark.slow
def test_policy_run_drives_an_artefact_as_it_ships_and_bare_without(tmp_path, artefact):
    import json
    import shutil

    shipped = tmp_path / "shipped"
    shutil.copytree(artefact, shipped)
    meta = json.loads((shipped / "metadata.json").read_text())
    (shipped / "metadata.json").write_text(json.dumps({**meta, "deploy": "+shield"}))
    result = curlnav("policy", "run", str(shipped), "--world", "open-room", "--pair", "across",
                     "--out", str(tmp_path / "a"), timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert f"{shipped}: driven as its artefact ships it, {shipped}+shield" in result.stdout
    assert "-shield-open-room-across.png" in result.stdout  # the picture names the stack it drove
    bare = curlnav("policy", "run", str(shipped), "--bare", "--world", "open-room", "--pair", "across",
                   "--out", str(tmp_path / "b"), timeout=300)
    assert bare.returncode == 0, bare.stderr[-2000:]
    assert "driven as its artefact ships it" not in bare.stdout and "-shield-" not in bare.stdout


# -- curlnav status ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def scheduler_status():
    """A real scheduler core on the paper's curriculum, in stage S2 with episodes, an actor and
    learner and replay figures, its ``status()`` served over HTTP like the scheduler's /status."""
    from curlnav.proto.messages import Assignment, AssignmentRequest, EpisodeReport, ServiceStatus
    from curlnav.scheduler.curriculum import load_curriculum
    from curlnav.scheduler.service import SchedulerCore

    core = SchedulerCore(load_curriculum(REPO / "scheduler" / "curricula" / "s1+s2.yaml"))
    assert core.force_advance()  # S1 -> S2, sub-step p1
    core.actor_joined("actor-0")
    assignment = Assignment.decode(core.assign(AssignmentRequest("actor-0").encode()))
    for i in range(6):
        core.report(EpisodeReport("actor-0", assignment.world, assignment.pair, i % 2 == 0, 1.0, 0, 0, 50, 7,
                                  assignment.epoch).encode())
    core.service_status(ServiceStatus("learner", {"version": 7, "updates": 1234, "updates_per_s": 21.5}).encode())
    core.service_status(ServiceStatus("replay", {"size": 4321, "insert_rate": 250.0}).encode())
    body = json.dumps(core.status()).encode()

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            code = 200 if self.path == "/status" else 404
            self.send_response(code)
            self.send_header("Content-Type", "application/json")
            self.end_headers()
            self.wfile.write(body if code == 200 else b"{}")

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}", json.loads(body)
    server.shutdown()
    server.server_close()


def assert_status_text(text: str) -> None:
    assert "curriculum s1+s2: stage 1 S2, sub-step 0 (pair p1)" in text
    assert "episodes 6: window success 50% over 6 episodes, advances at > 50% over 50 episodes" in text
    assert "learner: version 7, 1234 updates, 21.5 updates/s" in text
    assert "replay: 4321 transitions, 250 inserts/s" in text
    assert "live actors: 1" in text
    actor_row = next(line for line in text.splitlines() if line.strip().startswith("actor-0"))
    assert actor_row.split()[1:4] == ["t-maze-0", "p1", "6"]
    pair_row = next(line for line in text.splitlines() if line.strip().startswith("t-maze-0") and "%" in line)
    assert pair_row.split() == ["t-maze-0", "p1", "6", "50%"]
    assert "epoch 1: to stage S2 sub-step 0 after 0 episodes (forced by admin)" in text


@pytest.mark.net
@pytest.mark.slow
def test_status_from_the_scheduler_url(scheduler_status):
    url, _ = scheduler_status
    result = curlnav("status", url)  # no path: /status is added
    assert result.returncode == 0, result.stderr[-2000:]
    assert_status_text(result.stdout)


@pytest.mark.net
@pytest.mark.slow
def test_status_json_prints_the_scheduler_status_as_it_is(scheduler_status):
    url, status = scheduler_status
    result = curlnav("status", url + "/status", "--json")
    assert result.returncode == 0, result.stderr[-2000:]
    assert json.loads(result.stdout) == status


@pytest.mark.net
@pytest.mark.slow
def test_status_of_a_run_folder_and_of_the_newest_run_by_default(tmp_path, scheduler_status):
    url, _ = scheduler_status
    old, new = tmp_path / "runs" / "old-run", tmp_path / "runs" / "new-run"
    for folder, port in ((old, closed_port()), (new, int(url.rsplit(":", 1)[1]))):
        folder.mkdir(parents=True)
        (folder / "run.json").write_text(json.dumps({"status_url": f"http://127.0.0.1:{port}/status",
                                                     "learner_url": "http://127.0.0.1:1", "pid": os.getpid()}))
        time.sleep(0.05)  # distinct modification times
    (tmp_path / "runs" / "serial-run").mkdir()  # no run.json: not a candidate
    result = curlnav("status", str(new))
    assert result.returncode == 0, result.stderr[-2000:]
    assert_status_text(result.stdout)
    result = curlnav("status", cwd=tmp_path)  # the newest run folder under runs/ with a run.json
    assert result.returncode == 0, result.stderr[-2000:]
    assert_status_text(result.stdout)
    # a run whose scheduler is gone
    assert_one_line_error(curlnav("status", str(old)), "cannot reach http://127.0.0.1:", "is the run still going?")


@pytest.mark.slow
def test_status_of_a_folder_without_run_json(tmp_path):
    serial = tmp_path / "serial-run"
    serial.mkdir()
    assert_one_line_error(curlnav("status", str(serial)), f"no run.json in {serial}",
                          "serial runs have no scheduler")


@pytest.mark.net
@pytest.mark.slow
def test_status_of_an_unreachable_scheduler():
    port = closed_port()
    assert_one_line_error(curlnav("status", f"http://127.0.0.1:{port}"),
                          f"cannot reach http://127.0.0.1:{port}/status", "is the run still going?")


# -- replay files proportional to their content ----------------------------------------------------
REAL_LAYOUT = ObservationLayout.from_env_config(EnvConfig())


def fill(table: ReplayTable, transitions: int, episode_length: int = 100, seed: int = 0) -> None:
    """Insert ``transitions`` transitions of random episodes through the n-step writer."""
    rng = np.random.default_rng(seed)
    writer = NStepWriter(table.layout, n_step=3, discount=0.99)
    size = table.layout.size
    inserted = 0
    while inserted < transitions:
        steps = min(episode_length, transitions - inserted)
        writer.first(rng.uniform(0, 5, size).astype(np.float32))
        for t in range(steps):
            last = t == steps - 1
            writer.step(rng.uniform(-1, 1, 3), float(rng.normal()), rng.uniform(0, 5, size).astype(np.float32),
                        last and t % 2 == 0, last and t % 2 == 1)
        inserted += table.insert(writer.flush())


def same_counts(a: ReplayTable, b: ReplayTable) -> bool:
    fields = ("size", "max_size", "total_inserted", "total_sampled", "frames", "rejected", "sampler")
    return all(a.info()[f] == b.info()[f] for f in fields)


def assert_same_samples(a: ReplayTable, b: ReplayTable, n: int = 256) -> None:
    sa, sb = a.sample(n), b.sample(n)
    for field in ("keys", "obs", "next_obs", "action", "reward", "discount", "priorities", "probabilities",
                  "times_sampled"):
        assert np.array_equal(getattr(sa, field), getattr(sb, field)), field


def test_a_large_table_with_few_transitions_saves_small_and_restores(tmp_path):
    table = ReplayTable(REAL_LAYOUT, max_size=1_000_000, seed=5)
    fill(table, 3000)
    assert table.size == 3000
    path = table.save(tmp_path / "replay.npz")
    assert path.stat().st_size < 10 * 2**20, f"{path.stat().st_size / 2**20:.1f} MiB for 3000 transitions"
    restored = ReplayTable.restore(path, seed=5)
    assert restored.size == 3000 and restored.max_size == 1_000_000
    assert same_counts(restored, table)
    assert_same_samples(table, restored)
    # the restored table goes on: inserts and sampling after the restore
    fill(restored, 50, seed=1)
    assert restored.size == 3050 and restored.sample(64).obs.shape == (64, REAL_LAYOUT.size)


def test_a_full_table_whose_rings_wrapped_round_trips(tmp_path):
    table = ReplayTable(REAL_LAYOUT, max_size=200, frame_capacity=230, seed=2)
    fill(table, 700, episode_length=37)
    assert table.size <= 200 and table.info()["total_inserted"] == 700
    path = table.save(tmp_path / "replay.npz")
    restored = ReplayTable.restore(path, seed=2)
    again = ReplayTable.restore(restored.save(tmp_path / "again.npz"), seed=2)  # saved after a restore
    assert restored.size == table.size and same_counts(restored, table)
    assert_same_samples(table, restored)
    assert_same_samples(ReplayTable.restore(path, seed=2), again)


def test_a_prioritized_table_round_trips_its_priorities(tmp_path):
    table = ReplayTable(REAL_LAYOUT, max_size=500, sampler="prioritized", priority_exponent=0.6, seed=4)
    fill(table, 400)
    keys = np.arange(0, 400, 3)
    assert table.update_priorities(keys, np.linspace(0.01, 9.0, len(keys))) == len(keys)
    restored = ReplayTable.restore(table.save(tmp_path / "replay.npz"), seed=4)
    assert restored.sampler == "prioritized"
    assert_same_samples(table, restored, n=1000)


def test_a_replay_file_of_the_first_format_still_loads(tmp_path):
    """Version 1 files held every slot of the rings; they restore as they did."""
    table = ReplayTable(REAL_LAYOUT, max_size=300, seed=3)
    fill(table, 250)
    with np.load(table.save(tmp_path / "v2.npz"), allow_pickle=False) as data:
        meta = json.loads(bytes(data["meta"]).decode())
    meta["version"] = 1
    path = tmp_path / "v1.npz"
    np.savez(path, meta=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8),
             **{name: getattr(table, "_" + name) for name in ReplayTable._FRAME_ARRAYS + ReplayTable._TRANSITION_ARRAYS})
    restored = ReplayTable.restore(path, seed=3)
    assert restored.size == 250
    assert_same_samples(table, restored)


def test_a_replay_file_of_an_unknown_version_is_refused(tmp_path):
    table = ReplayTable(REAL_LAYOUT, max_size=10)
    with np.load(table.save(tmp_path / "replay.npz"), allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files}
    meta = json.loads(bytes(arrays["meta"]).decode())
    meta["version"] = 99
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez(tmp_path / "future.npz", **arrays)
    with pytest.raises(ValueError, match="version 99"):
        ReplayTable.restore(tmp_path / "future.npz")
