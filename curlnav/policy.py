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
        import onnxruntime as ort

        self.folder = Path(folder)
        meta_path = self.folder / "metadata.json"
        try:
            self.metadata = json.loads(meta_path.read_text())
        except FileNotFoundError:
            raise ArtefactError(f"{self.folder}: no metadata.json; not a policy artefact folder") from None
        except json.JSONDecodeError as exc:
            raise ArtefactError(f"{meta_path}: not valid JSON: {exc}") from None
        if self.metadata.get("format") != "curlnav-policy":
            raise ArtefactError(f"{meta_path}: format is {self.metadata.get('format')!r}, expected 'curlnav-policy'")
        for name, expected in self.metadata.get("files", {}).items():
            path = self.folder / name
            if not path.exists():
                raise ArtefactError(f"{self.folder}: missing {name}")
            if verify:
                actual = hashlib.sha256(path.read_bytes()).hexdigest()
                if actual != expected:
                    raise ArtefactError(f"{path}: sha256 {actual} does not match metadata ({expected})")
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        self.session = ort.InferenceSession(str(self.folder / "actor.onnx"), options,
                                            providers=["CPUExecutionProvider"])
        self.observation_size = int(self.metadata["observation"]["size"])

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
