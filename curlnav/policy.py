"""Load and run an exported policy artefact with ONNX Runtime (no training code involved)."""

from __future__ import annotations

import hashlib
import math
import os
import re
from pathlib import Path

import numpy as np

from curlnav.files import FileRefused, is_plain_file_name, read_json, shown
from curlnav.layout import MAX_MEMORY_BEAMS, MAX_MEMORY_RANGE, MAX_MEMORY_STEPS


class ArtefactError(ValueError):
    """The artefact folder is missing a file, has a bad checksum, or is not a curlnav policy."""


class PolicyArtefact:
    """``PolicyArtefact(folder)``; ``policy(obs) -> action`` for one observation or a batch."""

    def __init__(self, folder: str | Path, verify: bool = True) -> None:
        self.folder = Path(folder)
        self.metadata = self._read_metadata()
        meta_path = self.folder / "metadata.json"
        check_metadata(self.metadata, meta_path)  # every field a reader uses, before any is used
        verified: dict[str, str] = {}  # file name -> its sha256, read and matched here
        for name, expected in self._files(self.metadata, meta_path).items():
            path = self.folder / name
            if path.is_symlink() or not path.is_file():
                raise ArtefactError(f"{self.folder}: missing {name}" + (" (a symlink)" if path.is_symlink() else ""))
            if verify:
                actual = sha256_of(path)
                if actual != expected:
                    raise ArtefactError(f"{path}: sha256 {actual} does not match metadata ({expected})")
                verified[name] = actual
        self.observation_size = self.metadata["observation"]["size"]
        self.session = _onnx_session(self.folder / "actor.onnx", self.observation_size, verified.get("actor.onnx"))

    @classmethod
    def read_metadata(cls, folder: str | Path) -> dict:
        """``folder/metadata.json``, every field checked (``check_metadata``), without reading the
        files it lists nor opening the actor (``ArtefactError``, one line)."""
        artefact = cls.__new__(cls)
        artefact.folder = Path(folder)
        metadata = artefact._read_metadata()
        check_metadata(metadata, artefact.folder / "metadata.json")
        return metadata

    @classmethod
    def listed_files(cls, folder: str | Path) -> dict[str, str]:
        """``{file name: sha256}`` that ``folder/metadata.json`` lists, checked (plain names of the
        folder, 64 hex digits) without reading the files."""
        artefact = cls.__new__(cls)
        artefact.folder = Path(folder)
        return cls._files(artefact._read_metadata(), artefact.folder / "metadata.json")

    @staticmethod
    def _files(metadata: dict, meta_path: Path) -> dict[str, str]:
        files = metadata.get("files", {})
        if not isinstance(files, dict):
            raise ArtefactError(f"{meta_path}: 'files' must map file names to sha256 digests")
        for name, expected in files.items():  # only files of this folder: never a checksum of another
            if not is_plain_file_name(name) or name == "metadata.json":
                raise ArtefactError(f"{meta_path}: lists {shown(name)}, not a plain file name in the artefact folder")
            if not (isinstance(expected, str) and re.fullmatch(r"[0-9a-f]{64}", expected)):
                raise ArtefactError(f"{meta_path}: the sha256 of {name} is {shown(expected)}, not 64 hex digits")
        return files

    def _read_metadata(self) -> dict:
        expected = "expected a policy artefact folder (with metadata.json and actor.onnx)"
        if not self.folder.exists():
            raise ArtefactError(f"{self.folder}: no such folder; {expected}")
        if not self.folder.is_dir():
            raise ArtefactError(f"{self.folder}: a file, not a folder; {expected}")
        meta_path = self.folder / "metadata.json"
        try:
            metadata = read_json(meta_path, what="metadata.json")
        except FileNotFoundError:
            raise ArtefactError(f"{self.folder}: no metadata.json; not a policy artefact folder") from None
        except OSError as exc:
            raise ArtefactError(f"{meta_path}: cannot read: {exc.strerror or exc}") from None
        except FileRefused as exc:
            raise ArtefactError(str(exc)) from None
        if not isinstance(metadata, dict) or metadata.get("format") != "curlnav-policy":
            found = metadata.get("format") if isinstance(metadata, dict) else type(metadata).__name__
            raise ArtefactError(f"{meta_path}: format is {shown(found)}, expected 'curlnav-policy'")
        return metadata

    @property
    def version(self) -> int:
        return self.metadata.get("policy_version", 0)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        x = np.asarray(obs, dtype=np.float32)
        single = x.ndim == 1
        if x.shape[-1] != self.observation_size:
            raise ValueError(f"observation has {x.shape[-1]} values, the policy expects {self.observation_size}")
        out = self.session.run(["action"], {"observation": x[None] if single else x})[0]
        return out[0] if single else out


def sha256_of(path: Path) -> str:
    """The sha256 of a file, read 1 MiB at a time."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


# Bounds of an artefact's metadata (issue 35): a field outside them is refused in one line before
# anything reads it, so no reader (the ROS 2 node, the evaluator, the CLI) meets NaN, infinity, a
# zero period or a layout of a billion beams.
MAX_POLICY_VERSION = (1 << 63) - 1
MAX_BEAMS = 1 << 16  # beams of one scan
MAX_FRAMES = 256  # range, label or goal frames of one observation
MAX_RANGE_M = 1000.0
MAX_CONTROL_PERIOD_S = 60.0
MAX_SCALE = 100.0  # m/s, rad/s and m at action 1
MAX_ROBOT_SIZE_M = 100.0
MAX_ACTOR_BYTES = 256 << 20  # actor.onnx (an actor of the largest allowed networks is about 80 MB)
FIRST_ACTION_MEMORY_BYTES = 1 << 30  # address space of the process that runs the first action
FIRST_ACTION_TIMEOUT_S = 60.0


def _is_number(value, low: float, high: float, low_open: bool = True) -> bool:
    """A finite int or float (never a bool or a string) in ``(low, high]`` (``[low, high]`` when
    not ``low_open``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        value = float(value)
    except OverflowError:
        return False
    return math.isfinite(value) and (value > low if low_open else value >= low) and value <= high


def _is_whole(value, low: int, high: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high


def _numbers(value, n: int, low: float, high: float, low_open: bool = True) -> bool:
    return isinstance(value, list) and len(value) == n and all(_is_number(v, low, high, low_open) for v in value)


def _texts(value, n: int | None = None) -> bool:
    return isinstance(value, list) and (n is None or len(value) == n) and all(
        isinstance(v, str) and len(v) <= 1000 for v in value)


def check_metadata(metadata: dict, meta_path: Path) -> None:
    """Refuse (``ArtefactError``, one line naming the field) a ``metadata.json`` whose fields are
    not what ``curlnav.learner.artefact.export_policy`` writes: every number finite and within
    the bounds above, every list of its length, every field of its type."""
    def refuse(field: str, must: str, value) -> None:
        raise ArtefactError(f"{meta_path}: {field} must be {must}, got {shown(value)}")

    def section(name: str, required: bool = True) -> dict:
        value = metadata.get(name, None if required else {})
        if not isinstance(value, dict):
            refuse(name, "a mapping", value)
        return value

    if "version" in metadata and metadata["version"] != 1 or isinstance(metadata.get("version"), bool):
        refuse("version", "1 (the artefact format this curlnav reads)", metadata.get("version"))
    if not _is_whole(metadata.get("policy_version", 0), 0, MAX_POLICY_VERSION):
        refuse("policy_version", f"a whole number 0-{MAX_POLICY_VERSION}", metadata.get("policy_version"))
    if "created_unix_s" in metadata and not _is_number(metadata["created_unix_s"], 0, 1e11, low_open=False):
        refuse("created_unix_s", "a time in seconds since 1970", metadata["created_unix_s"])

    observation = section("observation")
    size = observation.get("size")
    if not _is_whole(size, 1, (1 << 24) - 1):
        refuse("observation.size", "a positive integer", size)
    layout = observation.get("layout")
    if not isinstance(layout, dict):
        refuse("observation.layout", "a mapping of beams, range_frames, label_frames, goal_frames, max_range", layout)
    for key, low, high in (("beams", 1, MAX_BEAMS), ("range_frames", 1, MAX_FRAMES), ("label_frames", 0, MAX_FRAMES),
                           ("goal_frames", 1, MAX_FRAMES)):
        if not _is_whole(layout.get(key), low, high):
            refuse(f"observation.layout.{key}", f"a whole number {low}-{high}", layout.get(key))
    if not _is_number(layout.get("max_range"), 0, MAX_RANGE_M):
        refuse("observation.layout.max_range", f"a distance above 0 and at most {MAX_RANGE_M:g} m", layout.get("max_range"))
    if layout.get("memory_beams", 0):  # the network's memory (curlnav.memory)
        for key, low, high in (("memory_beams", 1, MAX_MEMORY_BEAMS), ("memory_steps", 1, MAX_MEMORY_STEPS),
                               ("memory_stride", 1, MAX_MEMORY_STEPS)):
            if not _is_whole(layout.get(key), low, high):
                refuse(f"observation.layout.{key}", f"a whole number {low}-{high}", layout.get(key))
        if not _is_number(layout.get("memory_range"), 0, MAX_MEMORY_RANGE):
            refuse("observation.layout.memory_range", f"a distance above 0 and at most {MAX_MEMORY_RANGE:g} m",
                   layout.get("memory_range"))
    elif not _is_whole(layout.get("memory_beams", 0), 0, 0):
        refuse("observation.layout.memory_beams", "a whole number (0: no memory)", layout.get("memory_beams"))
    layout_size = ((layout["range_frames"] + layout["label_frames"]) * layout["beams"] + 3 * layout["goal_frames"]
                   + layout.get("memory_beams", 0))
    if layout_size != size:
        raise ArtefactError(f"{meta_path}: observation.layout gives {layout_size} values, observation.size says {size}")
    if not _is_number(observation.get("lidar_fov_rad"), 0, 2 * math.pi):
        refuse("observation.lidar_fov_rad", "an angle above 0 and at most 2 pi", observation.get("lidar_fov_rad"))
    if not _is_number(observation.get("control_period_s"), 0, MAX_CONTROL_PERIOD_S):
        refuse("observation.control_period_s", f"a period above 0 and at most {MAX_CONTROL_PERIOD_S:g} s",
               observation.get("control_period_s"))
    if "order" in observation and not _texts(observation["order"]):
        refuse("observation.order", "a list of texts", observation["order"])

    action = section("action")
    for key in ("low", "high"):
        if not _numbers(action.get(key), 3, -1e6, 1e6):
            refuse(f"action.{key}", "3 finite numbers", action.get(key))
    if not all(lo < hi for lo, hi in zip(action["low"], action["high"])):
        refuse("action.low", "below action.high", action["low"])
    if not _numbers(action.get("scale"), 3, 0, MAX_SCALE):
        refuse("action.scale", f"3 finite numbers above 0 and at most {MAX_SCALE:g} (m/s, rad/s, m)", action.get("scale"))
    for key in ("names", "units"):
        if key in action and not _texts(action[key], 3):
            refuse(f"action.{key}", "3 texts", action[key])

    robot = section("robot", required=False)
    for key, value in robot.items():
        if key == "name":  # the profile's name (curlnav.sim.robots)
            if not (isinstance(value, str) and re.fullmatch(r"[a-z0-9][a-z0-9_-]{0,39}", value)):
                refuse("robot.name", "a profile name (1-40 of a-z, 0-9, - and _)", value)
            continue
        if key == "arm":
            if not isinstance(value, bool):
                refuse("robot.arm", "true or false", value)
            continue
        if not _is_number(value, 0, MAX_ROBOT_SIZE_M):
            refuse(f"robot.{shown(key, 40)[1:-1]}", f"a finite number above 0 and at most {MAX_ROBOT_SIZE_M:g}", value)
    training = section("training", required=False)
    for key in ("learner_steps", "env_steps"):
        if key in training and not _is_whole(training[key], 0, MAX_POLICY_VERSION):
            refuse(f"training.{key}", "a whole number of steps", training[key])
    for key in ("curriculum_stage", "preset", "curriculum"):
        if key in training and not isinstance(training[key], str):
            refuse(f"training.{key}", "a text", training[key])
    if "worlds" in training and not _texts(training["worlds"]):
        refuse("training.worlds", "a list of world names", training["worlds"])


def _external_tensors(graph) -> list[str]:
    """Names of the tensors of ``graph`` (an ``onnx.GraphProto`` or ``FunctionProto``, its nodes'
    attributes and their subgraphs) whose data lies in an external file."""
    from onnx import AttributeProto, TensorProto

    def external(tensor) -> bool:
        return tensor.data_location == TensorProto.EXTERNAL or len(tensor.external_data) > 0

    found = [t.name for t in getattr(graph, "initializer", ()) if external(t)]  # a FunctionProto has none
    for sparse in getattr(graph, "sparse_initializer", ()):
        found += [t.name or "a sparse initializer" for t in (sparse.values, sparse.indices) if external(t)]
    for node in graph.node:
        for attr in node.attribute:
            tensors = [attr.t] if attr.type == AttributeProto.TENSOR else list(attr.tensors)
            if attr.type == AttributeProto.SPARSE_TENSOR:
                tensors += [attr.sparse_tensor.values, attr.sparse_tensor.indices]
            found += [t.name or f"{node.op_type} {attr.name}" for t in tensors if external(t)]
            for sub in ([attr.g] if attr.type == AttributeProto.GRAPH else list(attr.graphs)):
                found += _external_tensors(sub)
    return found


def _check_self_contained(path: Path) -> None:
    """Refuse an ``actor.onnx`` above ``MAX_ACTOR_BYTES`` or with external data (a tensor read from
    another file: one beside it that no checksum covers, or ``../secret.txt`` returned as the
    action), read without loading any external data."""
    import onnx
    from google.protobuf.message import DecodeError

    size = path.stat().st_size
    if size > MAX_ACTOR_BYTES:
        raise ArtefactError(f"{path}: {size} bytes, above the {MAX_ACTOR_BYTES >> 20} MiB cap of an actor")
    try:
        model = onnx.load(str(path), load_external_data=False)
    except (DecodeError, ValueError, RuntimeError, RecursionError) as exc:
        raise ArtefactError(f"{path}: not a loadable ONNX model ({shown(str(exc), 120)[1:-1]})") from None
    external = _external_tensors(model.graph)
    for function in model.functions:  # the same walk: tensors, sparse tensors, subgraphs
        external += [f"{function.name}: {name}" for name in _external_tensors(function)]
    if external:
        raise ArtefactError(f"{path}: {len(external)} tensor(s) with external data ({shown(external[:3], 120)}); a policy "
                            "actor.onnx must hold all its weights itself; refused")


_FIRST_ACTION = """import resource, sys
hard = resource.getrlimit(resource.RLIMIT_AS)[1]  # never above a lower limit of the parent's (ulimit -v)
bound = int(sys.argv[3]) if hard == resource.RLIM_INFINITY else min(int(sys.argv[3]), hard)
resource.setrlimit(resource.RLIMIT_AS, (bound, bound))
import numpy as np
import onnxruntime as ort

options = ort.SessionOptions()
options.intra_op_num_threads = options.inter_op_num_threads = 1
options.log_severity_level = 4
session = ort.InferenceSession(sys.argv[1], options, providers=["CPUExecutionProvider"])
action = session.run(["action"], {"observation": np.zeros((1, int(sys.argv[2])), np.float32)})[0]
print(repr(action.shape), repr([float(v) for v in np.ravel(action)[:8]]))
"""


_FIRST_ACTION_PASSED: set[tuple[str, int]] = set()  # (sha256 of actor.onnx, observation size) checked in this process


def _first_action_bounded(path: Path, size: int, sha256: str | None = None) -> None:
    """Open ``path`` and run its first action (a zero observation) in a child process whose
    address space is ``FIRST_ACTION_MEMORY_BYTES`` (or the lower hard limit this process has),
    within ``FIRST_ACTION_TIMEOUT_S``: a graph that allocates gigabytes at session start or at its
    first action is refused here, in one line, instead of taking this process (a robot's node)
    down. The action must be (1, 3), finite. A pass is remembered for the process by the sha256 of
    ``path`` (``sha256``: already read from this very file by the caller, else read here) and
    ``size``: loading the same artefact again does not run the child again."""
    import subprocess
    import sys

    key = (sha256 or sha256_of(path), size)
    if key in _FIRST_ACTION_PASSED:
        return
    bound = f"{FIRST_ACTION_MEMORY_BYTES >> 20} MiB"
    try:
        # one thread each: a BLAS or ONNX Runtime pool sized to a many-core machine must not fill the bound
        threads = {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
        result = subprocess.run([sys.executable, "-c", _FIRST_ACTION, str(path), str(size), str(FIRST_ACTION_MEMORY_BYTES)],
                                capture_output=True, text=True, timeout=FIRST_ACTION_TIMEOUT_S,
                                env={**os.environ, **threads})
    except subprocess.TimeoutExpired:
        raise ArtefactError(f"{path}: its first action took over {FIRST_ACTION_TIMEOUT_S:g} s; refused") from None
    if result.returncode != 0:
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        reason = lines[-1].split(" : ")[-1] if lines else f"exit status {result.returncode}"
        raise ArtefactError(f"{path}: opening it and its first action failed within a {bound} memory bound "
                            f"({shown(reason, 160)[1:-1]}); refused")
    out = result.stdout.strip()
    if not out.startswith("(1, 3) [") or any(word in out for word in ("nan", "inf")):
        raise ArtefactError(f"{path}: its first action is {shown(out, 120)}, expected 3 finite numbers; refused")
    _FIRST_ACTION_PASSED.add(key)


def _onnx_session(path: Path, size: int, sha256: str | None = None):
    """An ONNX Runtime session on ``path`` with the artefact's input and output names, or
    ``ArtefactError`` naming the file: no external data, input ``observation`` (batch, ``size``),
    output ``action`` (batch, 3), and a first action that ran within a memory bound (``sha256``:
    the file's digest when the caller has just read it, so it is not read twice)."""
    import onnxruntime as ort
    from onnxruntime.capi.onnxruntime_pybind11_state import Fail, InvalidArgument, InvalidGraph, InvalidProtobuf, NoSuchFile

    _check_self_contained(path)
    _first_action_bounded(path, size, sha256)  # before this process opens it: opening may allocate too (constant folding)
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    try:
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except (Fail, InvalidArgument, InvalidGraph, InvalidProtobuf, NoSuchFile) as exc:
        reason = str(exc).splitlines()[0].split(" : ")[-1] if str(exc) else type(exc).__name__
        raise ArtefactError(f"{path}: not a loadable ONNX model ({reason})") from None
    inputs = {i.name: i.shape for i in session.get_inputs()}
    outputs = {o.name: o.shape for o in session.get_outputs()}
    if "observation" not in inputs or "action" not in outputs:
        raise ArtefactError(f"{path}: an ONNX model with inputs {list(inputs)} and outputs {list(outputs)}, "
                            "expected input 'observation' and output 'action'")
    if len(inputs["observation"]) != 2 or inputs["observation"][1] != size:
        raise ArtefactError(f"{path}: input 'observation' has shape {inputs['observation']}, expected (batch, {size})")
    return session
