"""The learner service: ``sgd_step`` fed by the replay service over Zenoh.

Pulls sampled batches (``replay/sample`` queries; a refusal from the rate limiter just means
"wait"), updates, publishes versioned ``Weights`` every ``publish_every`` updates and answers
``weights/latest`` for late joiners, checkpoints and resumes, exports policy artefacts and
serves them over HTTP: ``GET /policy/latest``, ``GET /policy/<version>`` (JSON with files and
sha256), ``GET /policy/<version>/<file>``, ``/healthz``, ``/metrics``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from prometheus_client import CollectorRegistry, Counter, Gauge
from safetensors.torch import save as safetensors_bytes

from curlnav.bus.service import Deployment, ServiceShell
from curlnav.bus.transport import RateMeter, json_response, reliable_publisher
from curlnav.config import ConfigError, ExperimentConfig, config_differences, config_to_dict
from curlnav.layout import ObservationLayout
from curlnav.proto.codec import ProtoError
from curlnav.proto.messages import PriorityUpdate, SampledBatch, ServiceStatus, Weights
from curlnav.sim.robots import sensor_metadata

from .artefact import export_policy, training_worlds
from .d4pg import (
    TensorBatch,
    check_resumed_layout,
    compile_networks,
    load_checkpoint,
    read_metrics,
    save_checkpoint,
    set_amp,
    sgd_step,
)
from .feed import BatchAssembler, SampleFeed, describe_device, resolve_device
from .init_from import inherited_stack

log = logging.getLogger("curlnav.learner")


@dataclass(frozen=True)
class LearnerServiceConfig:
    """Deployment of the learner service (what it learns comes from the experiment config)."""

    deployment: Deployment = Deployment(data_dir="runs/service/learner")
    publish_every: int = 50  # updates between weight broadcasts
    checkpoint_every_s: float = 30.0  # a crash loses at most this much learning (s)
    export_every_s: float = 120.0
    keep_artefacts: int = 5  # newest artefact versions kept on disk
    torch_threads: int = 1  # on 2 cores shared with actors, 1 thread ran 31 updates/s, 2 threads 22
    device: str = "auto"  # auto: cuda when a GPU is present, else cpu
    in_flight: int = 4  # sample queries outstanding at the replay (it gathers the next while one travels)
    prefetch: int = 4  # decoded batches waiting (as tensors on the device)
    #: batches in one sample request: 4 took sampling beside inserts at full speed from 31k to 70-86k
    #: transitions/s on 2 cores (`curlnav bench transport --per-request`)
    batches_per_request: int = 4
    compile: str = "off"  # torch.compile of the networks: off | default | reduce-overhead (CUDA graphs)
    amp: str = "off"  # off | bf16: forward passes under bfloat16 autocast (measure first: `curlnav bench learner --check-amp`)
    priority_every: int = 4  # updates whose new priorities travel in one PriorityUpdate


class VersionMark:
    """The highest weights version published, in a file fsync'd at every publication: a learner
    restarted after a crash numbers its weights above it, so a version never names two weights."""

    WIDTH = 20

    def __init__(self, path: Path) -> None:
        self.path = path

    def read(self) -> int:
        try:
            return int(self.path.read_text().strip() or 0)
        except (OSError, ValueError):
            return 0

    def write(self, version: int) -> None:
        fd = os.open(self.path, os.O_WRONLY | os.O_CREAT, 0o644)
        try:
            os.pwrite(fd, f"{version:>{self.WIDTH}}\n".encode(), 0)  # one small in-place write
            os.fsync(fd)
        finally:
            os.close(fd)


def weights_message(state, version: int) -> Weights:
    tensors = {k: v.detach().cpu().contiguous() for k, v in state.actor.state_dict().items()}
    return Weights(version, state.steps, safetensors_bytes(tensors), state.config.to_dict())


class LearnerParts(Protocol):
    """What the learner service takes from the experiment's wiring (``curlnav.builder.D4PGBuilder``
    satisfies it; the service never imports the builder, which sits above it)."""

    layout: ObservationLayout

    def make_learner_state(self, device=None, say=print): ...

    def importance_weights(self, probabilities: np.ndarray, table_size: int) -> np.ndarray | None: ...

    def batches_per_request(self, wanted: int) -> int: ...


class LearnerService:
    def __init__(self, cfg: LearnerServiceConfig, experiment: ExperimentConfig, parts: LearnerParts) -> None:
        """``parts``: the experiment's wiring (``D4PGBuilder(experiment)``; its ``make_learner_service``
        hands itself in)."""
        self.cfg = cfg
        self.experiment = experiment
        self.parts = parts
        self.layout = parts.layout
        self.data_dir = Path(cfg.deployment.data_dir)
        (self.data_dir / "artefacts").mkdir(parents=True, exist_ok=True)
        torch.set_num_threads(cfg.torch_threads)
        self.device = resolve_device(cfg.device)
        log.info(describe_device(self.device))
        self.assembler = BatchAssembler(self.device)
        ckpt = self.data_dir / "latest.safetensors"
        self.version_mark = VersionMark(self.data_dir / "version")
        if ckpt.exists():
            self.state, extra = load_checkpoint(ckpt, self.device)
            if self.state.config != experiment.d4pg:
                diffs = config_differences(config_to_dict(self.state.config), config_to_dict(experiment.d4pg), "d4pg.")
                raise ConfigError(f"{ckpt} was trained with another d4pg config ({'; '.join(diffs[:3])}; checkpoint "
                                  f"first): use the run's config, or another data folder")
            check_resumed_layout(self.state, self.layout, ckpt, "data folder")
            # a new version for the restored weights, above every version ever published (a crash
            # may have published versions after this checkpoint): versions only go forward
            self.version = max(int(extra.get("version", 0)), self.version_mark.read(), *self.artefact_versions()) + 1
            self.version_mark.write(self.version)
            log.info("resumed from %s at %d updates (checkpoint version %d), now weights version %d", ckpt,
                     self.state.steps, int(extra.get("version", 0)), self.version)
        else:  # fresh networks, or the experiment's init_from (checked: ValueError, one line, exit 2)
            self.state = parts.make_learner_state(self.device, say=log.info)
            # no checkpoint, but a crash may have come after versions went out: go on above them
            published = max(self.version_mark.read(), *self.artefact_versions(), 0)
            self.version = published + 1 if published else 0
        set_amp(compile_networks(self.state, cfg.compile), cfg.amp)
        # on a GPU an update never waits for the device: metrics are read once per status period
        self.sync_every_update = self.device.type != "cuda"
        self.registry = CollectorRegistry()
        self.m_updates = Counter("learner_updates", "SGD steps", registry=self.registry)
        self.m_version = Gauge("learner_weights_version", "latest published weights version", registry=self.registry)
        self.m_rejected = Counter("learner_messages_rejected", "refused replies", ["reason"], registry=self.registry)
        self.m_loss = Gauge("learner_critic_loss", "last critic loss", registry=self.registry)
        self.m_version.set_function(lambda: self.version)
        self.update_rate = RateMeter()
        self.latest_weights: bytes = weights_message(self.state, self.version).encode()
        self.metrics: dict = {}  # the last update's metrics (on CUDA: tensors on the device)
        self.pending_priorities: list[PriorityUpdate] = []  # for the replay, when prioritized
        self.stop = threading.Event()
        self.started = time.monotonic()
        # what artefacts name as their training (worlds, curriculum): fixed for the run, read once
        self.artefact_training = training_worlds(self.experiment.curriculum.world, self.experiment.curriculum.file)
        # a fine-tuned policy ships behind the stack of the policy it started from
        self.artefact_stack = inherited_stack(self.experiment.init_from)

    # -- pure parts ----------------------------------------------------------------------------
    def learn_from(self, payload: bytes | SampledBatch, tensors: TensorBatch | None = None) -> dict:
        """One update from a sampled batch (a raw ``SampledBatch`` message, checked against the
        layout, or one the feed decoded, with its tensors). Returns its metrics: floats on CPU,
        0-d tensors on the device on CUDA (``read_metrics`` turns them into floats)."""
        batch = payload if isinstance(payload, SampledBatch) else SampledBatch.decode(payload, self.layout)
        if tensors is None:
            tensors = self.assembler(batch)
        weights = self.parts.importance_weights(batch.probabilities, self.replay_size)
        if weights is not None:
            tensors.weights = torch.as_tensor(weights, dtype=torch.float32).to(self.device)
        self.state, self.metrics, item_loss = sgd_step(self.state, tensors, sync=self.sync_every_update)
        if self.experiment.replay.prioritized:
            loss = item_loss if isinstance(item_loss, np.ndarray) else item_loss.float().cpu().numpy()
            self.pending_priorities.append(PriorityUpdate(batch.keys.copy(), (loss + 1e-6).astype(np.float32)))
        self.m_updates.inc()
        self.update_rate.add()
        if self.sync_every_update:
            self.read_losses()
        return self.metrics

    replay_size = 1  # transitions in the replay, from its status (importance weights)
    env_steps = 0  # transitions the replay has accepted in the whole run, from its status

    def publish_version(self) -> bytes:
        self.version += 1
        self.version_mark.write(self.version)  # on disk before anyone can see it
        self.latest_weights = weights_message(self.state, self.version).encode()
        return self.latest_weights

    def checkpoint(self) -> None:
        save_checkpoint(self.state, self.data_dir / "latest.safetensors",
                        extra={"version": self.version, **sensor_metadata(self.experiment.env),
                               **({"stack": self.artefact_stack} if self.artefact_stack else {})})

    def export(self) -> Path:
        folder = self.data_dir / "artefacts" / f"v{self.version}"
        worlds, extra = self.artefact_training
        export_policy(self.state, folder, self.experiment.env, worlds=worlds, extra=extra,
                      version=self.version, env_steps=self.env_steps, stack=self.artefact_stack)
        versions = sorted(self.artefact_versions())
        for old in versions[:-self.cfg.keep_artefacts]:
            shutil.rmtree(self.data_dir / "artefacts" / f"v{old}", ignore_errors=True)
        return folder

    def artefact_versions(self) -> list[int]:
        out = []
        for p in (self.data_dir / "artefacts").glob("v*"):
            if p.is_dir() and p.name[1:].isdigit() and (p / "metadata.json").exists():
                out.append(int(p.name[1:]))
        return out

    def read_losses(self) -> None:
        """The last update's metrics as floats, for ``status`` and the loss gauge: called by the
        learner's loop (on CUDA the metrics are tensors on the device until then), never from the
        HTTP thread, which only reads ``last_metrics``."""
        self.last_metrics = read_metrics(self.metrics)
        if "losses/critic" in self.last_metrics:
            self.m_loss.set(self.last_metrics["losses/critic"])

    last_metrics: dict[str, float] = {}  # the metrics as floats at the last read_losses

    def status(self) -> dict:
        metrics = self.last_metrics
        losses = {name: float(metrics[key]) for name, key in (("critic_loss", "losses/critic"),
                                                              ("actor_loss", "losses/actor"),
                                                              ("q_mean", "values/q_mean")) if key in metrics}
        return {"version": self.version, "updates": self.state.steps, "updates_per_s": self.update_rate.rate(),
                "env_steps": self.env_steps, "uptime_s": time.monotonic() - self.started, **losses}

    # -- HTTP ------------------------------------------------------------------------------------
    def _policy(self, request) -> tuple[int, str, bytes]:
        """Artefacts only from real folders and files inside ``<data_dir>/artefacts``: a symlink
        anywhere on the way (version folder or file) or a path resolving outside is a 404."""
        base = self.data_dir / "artefacts"
        root = os.path.realpath(base)

        def inside(path: Path, folder: bool) -> bool:  # no symlink, resolves where it lies, right kind
            real = os.path.realpath(path)
            return (not path.is_symlink() and real == os.path.join(root, *path.relative_to(base).parts)
                    and (os.path.isdir(real) if folder else os.path.isfile(real)))

        def folder_of(v: int) -> Path:
            return base / f"v{v}"

        parts = request.path.strip("/").split("/")  # policy, <version|latest>[, file]
        versions = [v for v in self.artefact_versions() if inside(folder_of(v), folder=True)
                    and inside(folder_of(v) / "metadata.json", folder=False)]
        if len(parts) < 2:
            return json_response({"error": "use /policy/latest or /policy/<version>"}, 404)
        if parts[1] == "latest":
            if not versions:
                return json_response({"error": "no policy exported yet"}, 404)
            version = max(versions)
        elif re.fullmatch(r"v?[0-9]{1,12}", parts[1]):
            version = int(parts[1].lstrip("v"))
        else:
            return json_response({"error": f"bad version {parts[1][:40]!r}"}, 400)
        folder = folder_of(version)
        if version not in versions:
            return json_response({"error": f"no policy version {version}", "available": sorted(versions)}, 404)
        try:
            meta = json.loads((folder / "metadata.json").read_text())
            listed = set(meta["files"]) | {"metadata.json"}
        except (OSError, ValueError, KeyError, TypeError):
            return json_response({"error": f"policy version {version} is unreadable"}, 404)
        if len(parts) == 2:
            files = {name: {"sha256": sha, "url": f"/policy/{version}/{name}"} for name, sha in meta["files"].items()}
            files["metadata.json"] = {"sha256": hashlib.sha256((folder / "metadata.json").read_bytes()).hexdigest(),
                                      "url": f"/policy/{version}/metadata.json"}  # pull requires one for every file
            return json_response({"version": version, "files": files, "metadata": meta})
        name = parts[2]
        if len(parts) != 3 or name not in listed or name in ("", ".", "..") or not inside(folder / name, folder=False):
            return json_response({"error": f"no file {'/'.join(parts[2:])[:200]!r} in version {version}"}, 404)
        return 200, "application/octet-stream", (folder / name).read_bytes()

    # -- shell -----------------------------------------------------------------------------------
    def run(self) -> None:
        cfg = self.cfg
        shell = ServiceShell("learner", "0", cfg.deployment, self.experiment, self.registry, self.status)
        with shell:
            session = shell.open({("GET", "/policy/"): self._policy})
            topo = shell.topology
            weights_pub = reliable_publisher(session, topo.weights)
            priorities_pub = reliable_publisher(session, topo.priorities)
            status_pub = session.declare_publisher(topo.status("learner"))
            latest_q = session.declare_queryable(topo.weights_latest,
                                                 lambda q: q.reply(topo.weights_latest, self.latest_weights))
            shell.on_close("weights queryable", latest_q.undeclare)
            replay_status = session.declare_subscriber(topo.status("replay"), self._on_replay_status)
            shell.on_close("replay status subscriber", replay_status.undeclare)
            if not self.artefact_versions():
                self.export()
            weights_pub.put(self.latest_weights)
            feed = SampleFeed(session, topo.sample, self.experiment.d4pg.batch_size, self.layout,
                              in_flight=cfg.in_flight, depth=cfg.prefetch, assembler=self.assembler,
                              batches_per_request=self.parts.batches_per_request(cfg.batches_per_request),
                              on_reject=lambda reason: self.m_rejected.labels(reason).inc()).start()
            last_status = last_ckpt = last_export = time.monotonic()
            try:
                while not self.stop.is_set():
                    item = feed.get(timeout=0.2)
                    got = item is not None
                    if got:
                        self.learn_from(*item)
                    if len(self.pending_priorities) >= cfg.priority_every or (self.pending_priorities and not got):
                        priorities_pub.put(PriorityUpdate.merge(self.pending_priorities).encode())
                        self.pending_priorities = []
                    if got and self.state.steps % cfg.publish_every == 0:
                        weights_pub.put(self.publish_version())
                    now = time.monotonic()
                    if now - last_status >= 1.0:
                        self.read_losses()
                        status_pub.put(ServiceStatus("learner", self.status()).encode())
                        last_status = now
                    if now - last_ckpt >= cfg.checkpoint_every_s:
                        self.checkpoint()
                        last_ckpt = now
                    if now - last_export >= cfg.export_every_s:
                        self.export()
                        last_export = now
            finally:
                self.stop.set()
                feed.close()
                self.checkpoint()
                self.export()
                log.info("learner stopped at %d updates, version %d", self.state.steps, self.version)

    def _on_replay_status(self, sample) -> None:
        try:
            values = ServiceStatus.decode(sample.payload.to_bytes()).values
            self.replay_size = max(int(values.get("size", 1)), 1)
            self.env_steps = max(int(values.get("inserted", 0)), self.env_steps)
        except ProtoError as exc:
            self.m_rejected.labels(exc.reason).inc()
