"""Actor and distributional critic over the paper's observation.

Both take the flat observation ``(B, layout.size)`` (see ``curlnav.layout``): scans and labels
go through an encoder, the memory's ring (``curlnav.memory``, where the layout has one, scaled by
its reach) and the goal history are concatenated, then an ELU MLP.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load as safetensors_load
from torch import nn

from curlnav.config import INFERENCE_BACKENDS, D4PGConfig
from curlnav.layout import ObservationLayout

MAX_NETWORK_PARAMETERS = 20_000_000  # of the actor or the critic: 80 MB of float32 each


def check_network_size(layout: ObservationLayout, cfg: D4PGConfig) -> None:
    """Refuse (``ValueError``) networks of more than ``MAX_NETWORK_PARAMETERS`` each, counted on
    the meta device: nothing is allocated. Call before making the networks of a layout and a
    config that came from outside (a checkpoint, a weights message, a config file)."""
    with torch.device("meta"):
        sizes = {name: sum(p.numel() for p in net(layout, cfg).parameters())
                 for name, net in (("actor", Actor), ("critic", DistributionalCritic))}
    for name, size in sizes.items():
        if size > MAX_NETWORK_PARAMETERS:
            raise ValueError(f"the {name} of d4pg.hidden {list(cfg.hidden)}, d4pg.encoder {cfg.encoder} and layout "
                             f"{layout.to_dict()} has {size:,} parameters, above the {MAX_NETWORK_PARAMETERS:,} limit")


# Action bounds of NamoEnv: v in [0, 1], w in [-1, 1], L in [0, 1].
ACTION_LOW = (0.0, -1.0, 0.0)
ACTION_HIGH = (1.0, 1.0, 1.0)


class ScanEncoder(nn.Module):
    """Flat observation -> feature vector ``(B, out_features)``."""

    def __init__(self, layout: ObservationLayout, cfg: D4PGConfig) -> None:
        super().__init__()
        self.layout = layout
        self.kind = cfg.encoder
        self.pool = cfg.pool
        b = layout.beams
        self._r_end = layout.range_frames * b
        self._l_end = self._r_end + layout.label_frames * b
        self._m_end = self._l_end + layout.memory_beams  # the memory's ring (curlnav.memory), if any
        if self.kind == "pooled":
            self.pad = (-b) % self.pool
            windows = (b + self.pad) // self.pool
            self.out_features = ((layout.range_frames + layout.label_frames) * windows + layout.memory_beams
                                 + 3 * layout.goal_frames)
        else:
            channels = layout.range_frames + layout.label_frames
            self.conv = nn.Sequential(nn.Conv1d(channels, cfg.conv_filters, 3), nn.ReLU(),
                                      nn.Conv1d(cfg.conv_filters, cfg.conv_filters, 3), nn.ReLU())
            self.out_features = cfg.conv_filters * (b - 4) + layout.memory_beams + 3 * layout.goal_frames

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        layout = self.layout
        bsz = obs.shape[0]
        ranges = obs[:, :self._r_end].reshape(bsz, layout.range_frames, layout.beams) / layout.max_range
        labels = obs[:, self._r_end:self._l_end].reshape(bsz, layout.label_frames, layout.beams)
        goal = obs[:, self._m_end:]
        if self._m_end > self._l_end:  # the ring, scaled to [0, 1] as the ranges are, beside the goal
            goal = torch.cat([obs[:, self._l_end:self._m_end] / layout.memory_range, goal], dim=1)
        if self.kind == "pooled":
            if self.pad:
                ranges = F.pad(ranges, (0, self.pad), value=1.0)
                labels = F.pad(labels, (0, self.pad), value=0.0)
            # min-pool ranges (nearest obstacle in each window), max-pool labels
            near = -F.max_pool1d(-ranges, self.pool)
            movable = F.max_pool1d(labels, self.pool)
            return torch.cat([near.flatten(1), movable.flatten(1), goal], dim=1)
        features = self.conv(torch.cat([ranges, labels], dim=1))
        return torch.cat([features.flatten(1), goal], dim=1)


def mlp(sizes: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.ELU())
    return nn.Sequential(*layers)


class Actor(nn.Module):
    """Deterministic policy: observation -> action inside ``[ACTION_LOW, ACTION_HIGH]``."""

    def __init__(self, layout: ObservationLayout, cfg: D4PGConfig, action_size: int = 3) -> None:
        super().__init__()
        self.encoder = ScanEncoder(layout, cfg)
        self.head = mlp([self.encoder.out_features, *cfg.hidden, action_size])
        self.register_buffer("low", torch.tensor(ACTION_LOW, dtype=torch.float32))
        self.register_buffer("high", torch.tensor(ACTION_HIGH, dtype=torch.float32))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.squash(self.preactivation(obs))

    def preactivation(self, obs: torch.Tensor) -> torch.Tensor:
        """The head's output before tanh (unbounded; the action is ``squash`` of it)."""
        return self.head(self.encoder(obs))

    def squash(self, preactivation: torch.Tensor) -> torch.Tensor:
        """tanh, scaled to ``[ACTION_LOW, ACTION_HIGH]``."""
        return self.low + (torch.tanh(preactivation) + 1.0) * 0.5 * (self.high - self.low)


class DistributionalCritic(nn.Module):
    """(observation, action) -> logits over ``atoms`` return values on ``[v_min, v_max]``."""

    def __init__(self, layout: ObservationLayout, cfg: D4PGConfig, action_size: int = 3) -> None:
        super().__init__()
        self.encoder = ScanEncoder(layout, cfg)
        self.head = mlp([self.encoder.out_features + action_size, *cfg.hidden, cfg.atoms])
        self.register_buffer("support", torch.linspace(cfg.v_min, cfg.v_max, cfg.atoms))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.head(torch.cat([self.encoder(obs), action], dim=1))

    def mean(self, logits: torch.Tensor) -> torch.Tensor:
        """Expected return of each row of logits."""
        return (torch.softmax(logits, dim=-1) * self.support).sum(-1)


def act(actor: Actor, obs: np.ndarray, sigma: float = 0.0, rng: np.random.Generator | None = None) -> np.ndarray:
    """The actor's action for one observation, plus Gaussian noise of ``sigma`` times each
    action's half-range, clipped to the action bounds."""
    device = next(actor.parameters()).device
    with torch.no_grad():
        action = actor(torch.as_tensor(obs, dtype=torch.float32, device=device)[None])[0].cpu().numpy()
    return explore(action, sigma, rng or np.random.default_rng())


def explore(actions: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """``actions`` (any shape ending in 3) plus Gaussian noise of ``sigma`` times each action's
    half-range, clipped to the action bounds, as float32."""
    if sigma > 0:
        low, high = np.asarray(ACTION_LOW), np.asarray(ACTION_HIGH)
        actions = np.clip(actions + rng.normal(0.0, sigma * (high - low) / 2, size=actions.shape), low, high)
    return actions.astype(np.float32)


class OnnxActorRunner:
    """The actor network on ONNX Runtime, one thread, for an actor process (issue 31): on one core
    beside PyBullet a batched call took 2.5-3x less time than PyTorch's (barn-3x3, 8
    environments: 78 us against 190-280 us per call).

    The graph is exported once from ``Actor`` (the one definition of the network; no constant
    folding, so its initializers keep the state-dict names), and ``load`` writes new weights into
    its initializers and opens a new session (about 5 ms; weights arrive about once a second)."""

    def __init__(self, network: Actor) -> None:
        import io

        import onnx

        buffer = io.BytesIO()
        example = torch.zeros(2, network.encoder.layout.size)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(network.cpu(), (example,), buffer, input_names=["observation"], output_names=["action"],
                              dynamic_axes={"observation": {0: "batch"}, "action": {0: "batch"}},
                              do_constant_folding=False, dynamo=False)
        self.model = onnx.load_from_string(buffer.getvalue())
        self._graph_bytes = buffer.getvalue()  # the exported graph: each load fills a fresh copy of it
        names = {init.name for init in self.model.graph.initializer}
        keys = set(network.state_dict())
        if names != keys:  # a weight folded into a constant would never follow a broadcast
            raise RuntimeError(f"the exported actor's initializers differ from its state dict: only in the graph "
                               f"{sorted(names - keys)}, only in the state dict {sorted(keys - names)}")
        self.session = None
        self.load(network.state_dict())

    def load(self, state_dict: dict[str, torch.Tensor]) -> None:
        import onnx
        import onnxruntime as ort
        from onnx import numpy_helper

        # A fresh message each time: protobuf keeps what a replaced field held for as long as the
        # message lives, so filling one message again and again grew an actor by 0.8 MB a load
        # (9 GB over a 4-hour run's 6000 broadcasts).
        model = onnx.load_from_string(self._graph_bytes)
        for init in model.graph.initializer:
            init.CopyFrom(numpy_helper.from_array(state_dict[init.name].detach().cpu().numpy(), init.name))
        self.model = model
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        options.log_severity_level = 3
        self.session = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Actions ``(K, 3)`` for float32 observations ``(K, size)``."""
        return self.session.run(None, {"observation": obs})[0]


class BehaviourPolicy:
    """What an actor runs (as Acme keeps the behaviour policy with the networks): uniformly
    random actions for its first ``warmup_steps`` steps or until it has weights, then the actor
    network plus Gaussian noise of ``sigma`` (a fraction of each action's half-range), clipped.

    The network is either shared (``use_network``: the serial trainer's live actor, run by
    PyTorch) or loaded from safetensors bytes (``load_weights``: the actor service), then run by
    ``inference``: ``onnx`` (``OnnxActorRunner``) or ``torch``. Actions are float32 ``(3,)``.
    """

    def __init__(self, layout: ObservationLayout, d4pg: D4PGConfig, sigma: float, warmup_steps: int,
                 rng: np.random.Generator, inference: str = "torch") -> None:
        if inference not in INFERENCE_BACKENDS:
            raise ValueError(f"inference {inference!r}: one of {', '.join(INFERENCE_BACKENDS)}")
        self.layout = layout
        self.d4pg = d4pg
        self.sigma = float(sigma)
        self.warmup_steps = int(warmup_steps)
        self.rng = rng
        self.inference = inference
        self.network: Actor | None = None
        self.runner: OnnxActorRunner | None = None  # the loaded weights on ONNX Runtime (inference onnx)
        self.steps = 0  # actions taken

    def use_network(self, network: Actor) -> None:
        self.network = network
        self.runner = None  # a live network changes under us: PyTorch runs it

    def load_weights(self, safetensors: bytes, d4pg: D4PGConfig | None = None) -> None:
        """Load actor weights (safetensors bytes); a network of ``d4pg``'s shape is made on
        first use. Raises if the tensors do not fit the network."""
        if self.network is None:
            check_network_size(self.layout, d4pg or self.d4pg)
            self.network = Actor(self.layout, d4pg or self.d4pg)
            self.network.eval()
        self.network.load_state_dict(safetensors_load(safetensors))  # checks every name and shape
        if self.inference == "onnx":
            try:
                if self.runner is None:
                    self.runner = OnnxActorRunner(self.network)
                else:
                    self.runner.load(self.network.state_dict())
            except Exception:
                self.runner = None  # never act with other weights than the network holds: PyTorch runs it
                raise

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        self.steps += 1
        if self.network is None or self.steps <= self.warmup_steps:
            return self.rng.uniform(ACTION_LOW, ACTION_HIGH).astype(np.float32)
        if self.runner is not None:
            return explore(self.runner(np.asarray(obs, dtype=np.float32)[None]), self.sigma, self.rng)[0]
        return act(self.network, obs, self.sigma, self.rng)

    def batch(self, obs: np.ndarray) -> np.ndarray:
        """Actions ``(K, 3)`` for observations ``(K, size)``: one forward pass for all K (the
        K steps count towards the warm-up; during it, uniformly random actions)."""
        obs = np.asarray(obs, dtype=np.float32)
        k = len(obs)
        self.steps += k
        if self.network is None or self.steps <= self.warmup_steps:
            return self.rng.uniform(ACTION_LOW, ACTION_HIGH, size=(k, len(ACTION_LOW))).astype(np.float32)
        if self.runner is not None:
            return explore(self.runner(obs), self.sigma, self.rng)
        device = next(self.network.parameters()).device
        with torch.no_grad():
            actions = self.network(torch.as_tensor(obs, device=device)).cpu().numpy()
        return explore(actions, self.sigma, self.rng)
