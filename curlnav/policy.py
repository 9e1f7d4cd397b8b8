"""Load and run an exported policy artefact with ONNX Runtime (no training code involved)."""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np

from curlnav.files import FileRefused, is_plain_file_name, read_json, shown


class ArtefactError(ValueError):
    """The artefact folder is missing a file, has a bad checksum, or is not a curlnav policy."""


class PolicyArtefact:
    """``PolicyArtefact(folder)``; ``policy(obs) -> action`` for one observation or a batch."""

    def __init__(self, folder: str | Path, verify: bool = True) -> None:
        self.folder = Path(folder)
        self.metadata = self._read_metadata()
        meta_path = self.folder / "metadata.json"
        for name, expected in self._files(self.metadata, meta_path).items():
            path = self.folder / name
            if path.is_symlink() or not path.is_file():
                raise ArtefactError(f"{self.folder}: missing {name}" + (" (a symlink)" if path.is_symlink() else ""))
            if verify:
                actual = sha256_of(path)
                if actual != expected:
                    raise ArtefactError(f"{path}: sha256 {actual} does not match metadata ({expected})")
        observation = self.metadata.get("observation")
        size = observation.get("size") if isinstance(observation, dict) else None
        if isinstance(size, bool) or not isinstance(size, int) or not 0 < size < 1 << 24:
            raise ArtefactError(f"{meta_path}: observation.size must be a positive integer, got {shown(size)}")
        self.observation_size = size
        version = self.metadata.get("policy_version", 0)
        if isinstance(version, bool) or not isinstance(version, int) or version < 0:
            raise ArtefactError(f"{meta_path}: policy_version must be a whole number, got {shown(version)}")
        self.session = _onnx_session(self.folder / "actor.onnx")

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
        return int(self.metadata.get("policy_version", 0))

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


def _onnx_session(path: Path):
    """An ONNX Runtime session on ``path`` with the artefact's input and output names, or
    ``ArtefactError`` naming the file."""
    import onnxruntime as ort
    from onnxruntime.capi.onnxruntime_pybind11_state import Fail, InvalidArgument, InvalidGraph, InvalidProtobuf, NoSuchFile

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    try:
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except (Fail, InvalidArgument, InvalidGraph, InvalidProtobuf, NoSuchFile) as exc:
        reason = str(exc).splitlines()[0].split(" : ")[-1] if str(exc) else type(exc).__name__
        raise ArtefactError(f"{path}: not a loadable ONNX model ({reason})") from None
    inputs = [i.name for i in session.get_inputs()]
    outputs = [o.name for o in session.get_outputs()]
    if "observation" not in inputs or "action" not in outputs:
        raise ArtefactError(f"{path}: an ONNX model with inputs {inputs} and outputs {outputs}, "
                            "expected input 'observation' and output 'action'")
    return session
