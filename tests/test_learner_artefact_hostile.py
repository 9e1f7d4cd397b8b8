"""Issue 35, artefacts, checkpoints and ``curlnav pull`` turned against their user: metadata that
would drive the robot with NaN or infinity, a checkpoint that asks for gigabytes, an actor.onnx
that reads a file beside (or outside) its folder or allocates 1e10 floats at its first action, and
a learner whose artefact never ends, in size or in time. Each ends in one ``curlnav: error:`` line
(exit 2) at a bounded cost, and nothing is kept.

Real processes: the CLI in a subprocess under an address-space cap (``conftest.run_capped``),
real ``http.server`` learners on loopback, real ONNX models built with ``onnx.helper``."""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from pathlib import Path

import numpy as np
import onnx
import pytest
from conftest import HostileLearner, assert_one_line_error
from conftest import run_capped as curlnav
from onnx import TensorProto, helper, numpy_helper

from curlnav.config import D4PGConfig
from curlnav.layout import ObservationLayout


def copy_artefact(source: Path, tmp_path: Path, change=None, name: str = "artefact") -> Path:
    """A copy of ``source`` whose metadata ``change(meta)`` edited (returning text replaces it)."""
    folder = tmp_path / name
    shutil.copytree(source, folder)
    if change is not None:
        meta = json.loads((folder / "metadata.json").read_text())
        text = change(meta)
        (folder / "metadata.json").write_text(text if isinstance(text, str) else json.dumps(meta))
    return folder


def relist(folder: Path) -> None:
    """Write the sha256 of every file of ``folder`` but metadata.json into its metadata."""
    meta = json.loads((folder / "metadata.json").read_text())
    meta["files"] = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())
                     if p.name != "metadata.json"}
    (folder / "metadata.json").write_text(json.dumps(meta))


def policy_run(folder: Path, tmp_path: Path):
    return curlnav("policy", "run", str(folder), "--world", "open-room", "--out", str(tmp_path / "run-out"))[0]


# -- metadata: every field checked before use ------------------------------------------------------

def _set(path: str, value):
    def change(meta):
        *parents, last = path.split(".")
        node = meta
        for key in parents:
            node = node[key]
        node[last] = value
    return change


HOSTILE_METADATA = {
    "scale-inf-nan": (_set("action.scale", ["inf", "nan", 0.5]), "action.scale"),
    "scale-short": (_set("action.scale", [1]), "action.scale"),
    "scale-negative": (_set("action.scale", [-1.0, 1.0, 0.5]), "action.scale"),
    "policy-version-huge": (lambda meta: json.dumps(meta).replace(f'"policy_version": {meta["policy_version"]}',
                                                                  '"policy_version": 1' + "0" * 4000), "policy_version"),
    "layout-a-list": (_set("observation.layout", [241, 4, 4, 10, 10.0]), "observation.layout"),
    "layout-beams-huge": (_set("observation.layout.beams", 10 ** 9), "observation.layout"),
    "layout-size-disagrees": (_set("observation.layout.goal_frames", 11), "observation"),
    "control-period-zero": (_set("observation.control_period_s", 0), "control_period_s"),
    "control-period-string": (_set("observation.control_period_s", "0.2"), "control_period_s"),
    "fov-nan": (_set("observation.lidar_fov_rad", "nan"), "lidar_fov_rad"),
    "low-above-high": (_set("action.low", [2.0, -1.0, 0.0]), "action.low"),
    "training-steps-text": (_set("training.env_steps", "many"), "training.env_steps"),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(HOSTILE_METADATA))
def test_hostile_metadata_is_refused_by_policy_run_in_one_line(artefact, tmp_path, case):
    change, field = HOSTILE_METADATA[case]
    folder = copy_artefact(artefact, tmp_path, change)
    assert_one_line_error(policy_run(folder, tmp_path), "metadata.json", field)


@pytest.mark.slow
def test_the_inf_nan_artefact_is_refused_by_eval_ros2_run_and_pull(artefact, tmp_path, learner):
    folder = copy_artefact(artefact, tmp_path, HOSTILE_METADATA["scale-inf-nan"][0])
    result = curlnav("eval", str(folder), "--world", "open-room", "--episodes", "1")[0]
    assert_one_line_error(result, "metadata.json", "action.scale")
    result = curlnav("ros2", "run", str(folder), "--loopback", "--duration-s", "5")[0]
    assert_one_line_error(result, "metadata.json", "action.scale")
    learner.serve_artefact(folder)
    out = tmp_path / "pulled" / "policy"
    assert_one_line_error(curlnav("pull", "--from", learner.url, "--out", str(out))[0], "metadata.json", "action.scale")
    assert not out.exists() and not list((tmp_path / "pulled").iterdir())


def test_the_shipped_policies_still_load():
    from curlnav.policy import PolicyArtefact

    root = Path(__file__).resolve().parents[1] / "policies"
    for folder in sorted(p for p in root.iterdir() if (p / "metadata.json").is_file()):
        policy = PolicyArtefact(folder)
        action = policy(np.zeros(policy.observation_size, dtype=np.float32))
        assert action.shape == (3,) and np.isfinite(action).all(), folder


# -- checkpoints: network sizes bounded before anything is allocated -------------------------------

def tiny_checkpoint(path: Path, config: dict, layout: dict) -> Path:
    """A checkpoint file of one float whose metadata asks for ``config``'s networks on ``layout``."""
    import torch
    from safetensors.torch import save_file

    meta = {"format": "curlnav-d4pg-checkpoint", "version": 1, "steps": 0, "config": config, "layout": layout,
            "actor_opt": {"param_groups": []}, "critic_opt": {"param_groups": []}, "extra": {}}
    save_file({"x": torch.zeros(1)}, str(path), metadata={"curlnav": json.dumps(meta)})
    return path


@pytest.mark.slow
def test_a_12000_wide_checkpoint_is_refused_fast_and_small(tmp_path):
    path = tiny_checkpoint(tmp_path / "wide.safetensors", D4PGConfig().to_dict() | {"hidden": [12000, 12000]},
                           ObservationLayout().to_dict())
    result, peak_mb, wall = curlnav("eval", str(path), "--world", "open-room", "--episodes", "1")
    print(f"{path.stat().st_size}-byte checkpoint of d4pg.hidden [12000, 12000]: {wall:.1f} s, peak {peak_mb:.0f} MB, "
          f"rc {result.returncode}: {result.stderr.strip()[:300]}")
    assert_one_line_error(result, str(path), "d4pg.hidden")
    # wall: the CLI's own time, its imports (torch) included: loose on a loaded machine; the
    # refusal itself is timed in-process below. The memory bound stays strict.
    assert wall < 20 and peak_mb < 1000


def test_the_refusal_of_a_12000_wide_checkpoint_itself_takes_under_10_s(tmp_path):
    from curlnav.learner.d4pg import load_checkpoint

    path = tiny_checkpoint(tmp_path / "wide.safetensors", D4PGConfig().to_dict() | {"hidden": [12000, 12000]},
                           ObservationLayout().to_dict())
    started = time.monotonic()
    with pytest.raises(ValueError, match="d4pg.hidden"):
        load_checkpoint(path, "cpu")
    assert time.monotonic() - started < 10


@pytest.mark.slow
@pytest.mark.parametrize("layout", [{"beams": 10 ** 7}, {"range_frames": 10 ** 6}, {"max_range": float("nan")},
                                    {"beams": "241"}])
def test_a_checkpoint_with_a_hostile_layout_is_refused_in_one_line(tmp_path, layout):
    path = tiny_checkpoint(tmp_path / "layout.safetensors", D4PGConfig().to_dict(), ObservationLayout().to_dict() | layout)
    result, peak_mb, wall = curlnav("eval", str(path), "--world", "open-room", "--episodes", "1")
    assert_one_line_error(result, str(path), "layout")
    assert wall < 20 and peak_mb < 1000  # wall includes Python's start and torch's import on a loaded machine


def test_the_config_bounds_network_sizes():
    from curlnav.config import ConfigError

    for bad in ({"hidden": (12000, 12000)}, {"hidden": (64,) * 50}, {"atoms": 10 ** 6}, {"conv_filters": 10 ** 5},
                {"pool": 10 ** 6}):
        with pytest.raises(ConfigError, match="d4pg"):
            D4PGConfig(**bad)
    from curlnav.learner.networks import check_network_size

    paper = D4PGConfig(preset="paper", encoder="conv", hidden=(512, 512, 256, 256))
    check_network_size(ObservationLayout(), paper)  # the paper's networks still fit
    with pytest.raises(ValueError, match="parameters"):  # each width allowed, the whole too big: counted, not made
        check_network_size(ObservationLayout(), D4PGConfig(hidden=(4096,) * 8))


# -- actor.onnx: no external data, a bounded first action ------------------------------------------

def test_the_image_requirements_are_at_least_the_project_floors():
    """docker/requirements.txt installs the image (curlnav itself with --no-deps): no floor or pin
    there may be below pyproject.toml's (onnxruntime>=1.18 let an escaping external path through)."""
    import tomllib

    from packaging.requirements import Requirement
    from packaging.version import Version

    root = Path(__file__).resolve().parents[1]

    def lowest(requirement: Requirement) -> Version | None:
        floors = [Version(s.version) for s in requirement.specifier if s.operator in (">=", "==", "~=", "===")]
        return max(floors, default=None)

    project = {r.name.lower(): r for r in map(Requirement,
                                               tomllib.loads((root / "pyproject.toml").read_text())["project"]["dependencies"])}
    image = {}
    for line in (root / "docker" / "requirements.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            requirement = Requirement(line)
            image[requirement.name.lower()] = requirement
    assert "onnxruntime" in image and "onnxruntime" in project
    low = [f"{name}: image {image[name].specifier or 'any'}, project {project[name].specifier}"
           for name in sorted(image.keys() & project.keys())
           if lowest(project[name]) is not None
           and (lowest(image[name]) is None or lowest(image[name]) < lowest(project[name]))]
    assert low == []


def external_data_model(folder: Path, location: str) -> None:
    """Replace ``folder/actor.onnx`` by a model whose one initializer is external data at
    ``location`` (relative to the folder): action = the first 3 floats of that file."""
    weights = TensorProto(name="w", data_type=TensorProto.FLOAT, dims=[3])
    weights.data_location = TensorProto.EXTERNAL
    for key, value in (("location", location), ("offset", "0"), ("length", "12")):
        entry = weights.external_data.add()
        entry.key, entry.value = key, value
    size = json.loads((folder / "metadata.json").read_text())["observation"]["size"]
    graph = helper.make_graph(
        [helper.make_node("Slice", ["observation", "start", "end", "axis"], ["first"]),
         helper.make_node("Mul", ["first", "zero"], ["nothing"]),
         helper.make_node("Add", ["nothing", "w"], ["action"])],
        "leak",
        [helper.make_tensor_value_info("observation", TensorProto.FLOAT, ["batch", size])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", 3])],
        [weights, numpy_helper.from_array(np.array([0], np.int64), "start"),
         numpy_helper.from_array(np.array([3], np.int64), "end"), numpy_helper.from_array(np.array([1], np.int64), "axis"),
         numpy_helper.from_array(np.zeros(1, np.float32), "zero")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    (folder / "actor.onnx").write_bytes(model.SerializeToString())


@pytest.mark.slow
def test_actor_onnx_with_external_data_in_its_own_folder_is_refused(artefact, tmp_path):
    folder = copy_artefact(artefact, tmp_path)
    (folder / "weights.bin").write_bytes(np.array([7.0, 7.0, 7.0], np.float32).tobytes())
    external_data_model(folder, "weights.bin")
    relist(folder)  # every file listed with its right sha256: only the external data is wrong
    assert_one_line_error(policy_run(folder, tmp_path), "actor.onnx", "external data")


@pytest.mark.slow
def test_actor_onnx_reading_a_file_outside_its_folder_never_shows_it(artefact, tmp_path):
    (tmp_path / "secret.txt").write_bytes(b"SECRETS!" * 4)
    folder = copy_artefact(artefact, tmp_path)
    external_data_model(folder, "../secret.txt")
    relist(folder)
    result = policy_run(folder, tmp_path)
    assert "SECRETS" not in result.stdout + result.stderr
    assert_one_line_error(result, "actor.onnx", "external data")


def bomb_model(folder: Path, floats: int) -> None:
    """Replace ``folder/actor.onnx`` by a model that allocates ``floats`` float32 at each action."""
    size = json.loads((folder / "metadata.json").read_text())["observation"]["size"]
    graph = helper.make_graph(
        [helper.make_node("ConstantOfShape", ["shape"], ["big"], value=helper.make_tensor("v", TensorProto.FLOAT, [1], [0.0])),
         helper.make_node("ReduceSum", ["big"], ["total"], keepdims=0),
         helper.make_node("Slice", ["observation", "start", "end", "axis"], ["first"]),
         helper.make_node("Mul", ["first", "zero"], ["nothing"]),
         helper.make_node("Add", ["nothing", "total"], ["action"])],
        "bomb",
        [helper.make_tensor_value_info("observation", TensorProto.FLOAT, ["batch", size])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", 3])],
        [numpy_helper.from_array(np.array([floats], np.int64), "shape"),
         numpy_helper.from_array(np.array([0], np.int64), "start"), numpy_helper.from_array(np.array([3], np.int64), "end"),
         numpy_helper.from_array(np.array([1], np.int64), "axis"), numpy_helper.from_array(np.zeros(1, np.float32), "zero")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    (folder / "actor.onnx").write_bytes(model.SerializeToString())


@pytest.mark.slow
def test_a_graph_that_allocates_1e10_floats_at_its_first_action_is_refused_in_one_line(artefact, tmp_path):
    folder = copy_artefact(artefact, tmp_path)
    bomb_model(folder, 10 ** 10)
    relist(folder)
    result, peak_mb, wall = curlnav("policy", "run", str(folder), "--world", "open-room",
                                    "--out", str(tmp_path / "run-out"))
    print(f"1e10-float graph: {wall:.1f} s, peak {peak_mb:.0f} MB, rc {result.returncode}")
    assert_one_line_error(result, "actor.onnx", "first action")
    assert peak_mb < 1000


FIRST_ACTION_CHILD = """import sys
from pathlib import Path
from curlnav.policy import _first_action_bounded
_first_action_bounded(Path(sys.argv[1]), int(sys.argv[2]))
print("first action ran")
"""


@pytest.mark.slow
def test_the_first_action_check_runs_under_a_lower_hard_memory_limit():
    """A process whose hard address-space limit is already below the 1 GiB bound (``ulimit -v``,
    some containers): the child keeps that limit instead of failing to raise it (ValueError)."""
    import resource
    import subprocess
    import sys

    from curlnav.policy import FIRST_ACTION_MEMORY_BYTES

    folder = Path(__file__).resolve().parents[1] / "policies" / "namo-general"
    size = json.loads((folder / "metadata.json").read_text())["observation"]["size"]
    limit = FIRST_ACTION_MEMORY_BYTES - (64 << 20)

    def lower_hard_limit():
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    result = subprocess.run([sys.executable, "-c", FIRST_ACTION_CHILD, str(folder / "actor.onnx"), str(size)],
                            capture_output=True, text=True, timeout=120, preexec_fn=lower_hard_limit)
    assert result.returncode == 0 and "first action ran" in result.stdout, result.stderr[-600:]


def function_model(path: Path, hidden) -> None:
    """An actor.onnx whose graph calls a local function, ``hidden(function)`` putting external
    data somewhere in that function's nodes."""
    from onnx import FunctionProto

    function = FunctionProto(name="scaled", domain="local", input=["x"], output=["y"])
    function.node.append(helper.make_node("Identity", ["x"], ["y"]))
    function.opset_import.append(helper.make_opsetid("", 17))
    hidden(function)
    graph = helper.make_graph([helper.make_node("scaled", ["observation"], ["action"], domain="local")], "g",
                              [helper.make_tensor_value_info("observation", TensorProto.FLOAT, ["batch", 3])],
                              [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", 3])])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid("local", 1)],
                              functions=[function])
    path.write_bytes(model.SerializeToString())


def external_tensor(name: str = "w") -> TensorProto:
    tensor = TensorProto(name=name, data_type=TensorProto.FLOAT, dims=[3])
    tensor.data_location = TensorProto.EXTERNAL
    for key, value in (("location", "../secret.txt"), ("offset", "0"), ("length", "12")):
        entry = tensor.external_data.add()
        entry.key, entry.value = key, value
    return tensor


def _in_tensors(function) -> None:
    attr = helper.make_attribute("weights", [external_tensor()])
    function.node.append(helper.make_node("Identity", ["x"], ["unused"]))
    function.node[-1].attribute.append(attr)


def _in_sparse(function) -> None:
    sparse = helper.make_sparse_tensor(external_tensor("values"), numpy_helper.from_array(np.array([0], np.int64), "i"),
                                       [3])
    function.node.append(helper.make_node("Constant", [], ["unused"], sparse_value=sparse))


def _in_subgraph(function) -> None:
    branch = helper.make_graph([helper.make_node("Constant", [], ["out"], value=external_tensor())], "branch", [],
                               [helper.make_tensor_value_info("out", TensorProto.FLOAT, [3])])
    function.node.append(helper.make_node("If", ["x"], ["unused"], then_branch=branch, else_branch=branch))


@pytest.mark.parametrize("where", [_in_tensors, _in_sparse, _in_subgraph], ids=["tensors", "sparse", "subgraph"])
def test_external_data_anywhere_in_an_onnx_function_is_refused(tmp_path, where):
    from curlnav.policy import ArtefactError, _check_self_contained

    path = tmp_path / "actor.onnx"
    function_model(path, where)
    with pytest.raises(ArtefactError, match="external data"):
        _check_self_contained(path)


def test_loading_the_same_artefact_again_does_not_rerun_the_first_action_check(artefact, tmp_path, monkeypatch):
    """The first-action child (about 1.5 s) runs once per actor.onnx content and observation size
    in a process: a second load of the same artefact skips it, a changed actor.onnx does not."""
    import subprocess

    from curlnav import policy
    from curlnav.policy import _FIRST_ACTION, PolicyArtefact

    monkeypatch.setattr(policy, "_FIRST_ACTION_PASSED", set())  # another module may have loaded these bytes
    children = []
    run = subprocess.run

    def counted(args, *more, **kwargs):
        if _FIRST_ACTION in args:
            children.append(args)
        return run(args, *more, **kwargs)

    monkeypatch.setattr(subprocess, "run", counted)
    folder = copy_artefact(artefact, tmp_path)
    PolicyArtefact(folder)
    PolicyArtefact(copy_artefact(artefact, tmp_path, name="again"))
    assert len(children) == 1
    bomb_model(folder, 10)  # another actor.onnx: checked again
    relist(folder)
    PolicyArtefact(folder)
    assert len(children) == 2


# -- curlnav pull: a total, a file count and a deadline --------------------------------------------

MIB = 1 << 20


def zeros_sha256(size: int) -> str:
    digest, chunk = hashlib.sha256(), b"\0" * MIB
    for _ in range(size // MIB):
        digest.update(chunk)
    return digest.hexdigest()


def serve_big_files(learner: HostileLearner, artefact: Path, sizes: dict[str, int]) -> None:
    """The artefact's listing, plus ``sizes`` files of zeros (streamed) that metadata.json and the
    listing both list with their right sha256."""
    def streamed(size):
        def write(wfile):
            chunk = b"\0" * MIB
            for _ in range(size // MIB):
                wfile.write(chunk)
        return write

    shas = {name: zeros_sha256(size) for name, size in sizes.items()}

    def big(listing):
        listing["metadata"]["files"].update(shas)
        meta = json.dumps(listing["metadata"]).encode()
        files = listing["files"] | {"metadata.json": {"sha256": hashlib.sha256(meta).hexdigest(), "url": "/files/meta"}}
        learner.routes["/files/meta"] = (200, {}, meta)
        for i, (name, size) in enumerate(sizes.items()):
            learner.routes[f"/files/big{i}"] = (200, {"Content-Length": str(size)}, streamed(size))
            files[name] = {"sha256": shas[name], "url": f"/files/big{i}"}
        listing["files"] = files

    learner.serve_artefact(artefact, listing_changes=big)


def test_a_pull_refuses_bad_metadata_before_any_other_file_comes_down(learner, artefact, tmp_path):
    """The inf/NaN metadata, listed with a 200 MiB file (right sha256s): refused from metadata.json
    alone; no other file is requested, so nothing of the 200 MiB comes down."""
    from curlnav.run.pull import pull_policy

    folder = copy_artefact(artefact, tmp_path, HOSTILE_METADATA["scale-inf-nan"][0])
    serve_big_files(learner, folder, {"big.bin": 200 * MIB})
    requested = []
    for path, (status, headers, body) in list(learner.routes.items()):
        if path.startswith("/files/"):
            def record(wfile, path=path, body=body):
                requested.append(path)
                body(wfile) if callable(body) else wfile.write(body)
            learner.routes[path] = (status, headers if callable(body) else {**headers, "Content-Length": str(len(body))},
                                    record)
    out = tmp_path / "pulled" / "policy"
    with pytest.raises(ValueError, match="action.scale"):
        pull_policy(learner.url, out)
    assert requested == ["/files/meta"]
    assert not out.exists() and not list((tmp_path / "pulled").iterdir())


@pytest.mark.slow
def test_a_pull_of_three_200_mib_files_is_refused_with_nothing_kept(learner, artefact, tmp_path):
    serve_big_files(learner, artefact, {"a.bin": 200 * MIB, "b.bin": 200 * MIB, "c.bin": 200 * MIB})
    out = tmp_path / "pulled" / "policy"
    result, peak_mb, wall = curlnav("pull", "--from", learner.url, "--out", str(out), timeout=300)
    print(f"pull of 3 x 200 MiB: {wall:.1f} s, peak {peak_mb:.0f} MB, rc {result.returncode}")
    assert_one_line_error(result, "--max-bytes")
    assert not out.exists() and not list((tmp_path / "pulled").iterdir())


@pytest.mark.slow
def test_a_pull_of_more_files_than_max_files_is_refused(learner, artefact, tmp_path):
    serve_big_files(learner, artefact, {f"part{i}.bin": MIB for i in range(5)})
    out = tmp_path / "pulled" / "policy"
    result = curlnav("pull", "--from", learner.url, "--out", str(out), "--max-files", "4")[0]
    assert_one_line_error(result, "--max-files")
    assert not (tmp_path / "pulled").exists()  # refused from the listing, before any folder


@pytest.mark.slow
@pytest.mark.parametrize("where", ["listing", "file"])
def test_a_pull_from_a_server_that_drips_a_byte_every_4_s_ends_at_the_deadline(learner, artefact, tmp_path, where):
    stop = []

    def drip(wfile):
        for _ in range(60):
            if stop:
                return
            wfile.write(b" ")
            wfile.flush()
            time.sleep(4)

    def slow(listing):
        if where == "file":
            learner.routes[listing["files"]["actor.onnx"]["url"]] = (200, {"Content-Length": "1000"}, drip)

    learner.serve_artefact(artefact, listing_changes=slow)
    if where == "listing":
        learner.routes["/policy/latest"] = (200, {"Content-Length": "1000"}, drip)
    out = tmp_path / "pulled" / "policy"
    try:
        began = time.monotonic()
        result = curlnav("pull", "--from", learner.url, "--out", str(out), "--deadline-s", "3", timeout=60)[0]
        took = time.monotonic() - began
    finally:
        stop.append(True)
    print(f"drip ({where}): gave up after {took:.1f} s")
    assert_one_line_error(result, "--deadline-s")
    assert took < 3 + 10  # the deadline, plus starting Python
    assert not out.exists()
    assert not (tmp_path / "pulled").exists() or not list((tmp_path / "pulled").iterdir())


@pytest.mark.slow
def test_pull_flags_refuse_nonsense(learner, artefact, tmp_path):
    learner.serve_artefact(artefact)
    for flag, value in (("--max-bytes", "0"), ("--max-files", "-1"), ("--deadline-s", "nan"), ("--deadline-s", "0")):
        result = curlnav("pull", "--from", learner.url, "--out", str(tmp_path / "p"), flag, value)[0]
        assert_one_line_error(result, flag)


def test_a_pull_goes_on_when_the_learner_drops_a_connection_before_replying(tmp_path):
    """A learner that closes a connection before any reply (restarting, or dropping a request it
    could not read in time) costs a pull a retry, not the pull: up to ``DROPPED_TRIES`` in all."""
    import socket
    import threading

    from curlnav.run.pull import DROPPED_TRIES, http_get

    def serve(drops: int) -> tuple[str, threading.Thread]:
        listener = socket.socket()
        listener.bind(("127.0.0.1", 0))
        listener.listen(8)
        listener.settimeout(5)

        def run():
            with listener:
                for i in range(drops + 1):
                    try:
                        conn, _ = listener.accept()
                    except OSError:  # the client gave up: nothing more to serve
                        return
                    with conn:
                        conn.recv(65536)
                        if i < drops:
                            continue  # closed without a byte of reply
                        conn.sendall(b"HTTP/1.0 200 OK\r\nContent-Length: 5\r\n\r\nhello")
                        return

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        return f"http://127.0.0.1:{listener.getsockname()[1]}/policy/latest", thread

    url, thread = serve(DROPPED_TRIES - 1)
    assert http_get(url, timeout=10) == b"hello"
    thread.join(10)
    url, thread = serve(DROPPED_TRIES)
    with pytest.raises(OSError, match="closed connection without response"):
        http_get(url, timeout=10)
