"""Load and run an exported policy artefact with ONNX Runtime (no training code involved)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np


class ArtefactError(ValueError):
    """The artefact folder is missing a file, has a bad checksum, or is not a curlnav policy."""


class PolicyArtefact:
    """``PolicyArtefact(folder)``; ``policy(obs) -> action`` for one observation or a batch."""

    def __init__(self, folder: str | Path, verify: bool = True) -> None:
        self.folder = Path(folder)
        self.metadata = self._read_metadata()
        files = self.metadata.get("files", {})
        if not isinstance(files, dict):
            raise ArtefactError(f"{self.folder / 'metadata.json'}: 'files' must map file names to sha256 digests")
        for name, expected in files.items():
            path = self.folder / name
            if not path.is_file():
                raise ArtefactError(f"{self.folder}: missing {name}")
            if verify:
                actual = hashlib.sha256(path.read_bytes()).hexdigest()
                if actual != expected:
                    raise ArtefactError(f"{path}: sha256 {actual} does not match metadata ({expected})")
        try:
            self.observation_size = int(self.metadata["observation"]["size"])
        except (KeyError, TypeError, ValueError):
            raise ArtefactError(f"{self.folder / 'metadata.json'}: no integer observation.size") from None
        self.session = _onnx_session(self.folder / "actor.onnx")

    def _read_metadata(self) -> dict:
        expected = "expected a policy artefact folder (with metadata.json and actor.onnx)"
        if not self.folder.exists():
            raise ArtefactError(f"{self.folder}: no such folder; {expected}")
        if not self.folder.is_dir():
            raise ArtefactError(f"{self.folder}: a file, not a folder; {expected}")
        meta_path = self.folder / "metadata.json"
        try:
            metadata = json.loads(meta_path.read_text())
        except FileNotFoundError:
            raise ArtefactError(f"{self.folder}: no metadata.json; not a policy artefact folder") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ArtefactError(f"{meta_path}: cannot read: {getattr(exc, 'strerror', None) or exc}") from None
        except json.JSONDecodeError as exc:
            raise ArtefactError(f"{meta_path}: not valid JSON: {exc}") from None
        if not isinstance(metadata, dict) or metadata.get("format") != "curlnav-policy":
            found = metadata.get("format") if isinstance(metadata, dict) else type(metadata).__name__
            raise ArtefactError(f"{meta_path}: format is {found!r}, expected 'curlnav-policy'")
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
