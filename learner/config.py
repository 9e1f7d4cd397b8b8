"""D4PG configuration: one documented, frozen dataclass, with two presets.

``D4PGConfig.default()`` is sized for a laptop CPU; ``D4PGConfig.paper()`` has the authors'
network. Costs, measured on one of our 2-core machines (PyTorch 2.13 CPU, batch 256), are
printed by ``curlnav bench learner`` and quoted in the README.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class D4PGConfig:
    preset: str = "default"
    # Observation encoder: "pooled" min-pools each range frame (max-pools each label frame)
    # over windows of `pool` beams and feeds an MLP; "conv" is the paper's trunk of two Conv1D
    # layers (32 filters, kernel 3, stride 1, ReLU) over the 8 stacked scan channels.
    encoder: str = "pooled"
    pool: int = 4  # beams per window for the pooled encoder (241 -> 61)
    conv_filters: int = 32
    hidden: tuple[int, ...] = (256, 256)  # MLP widths (ELU) of both actor and critic heads
    atoms: int = 51
    v_min: float = -50.0  # support of the return distribution; the goal reward is +200
    v_max: float = 250.0
    n_step: int = 5
    discount: float = 0.99
    batch_size: int = 256
    actor_lr: float = 1e-4
    critic_lr: float = 1e-4
    target_update_period: int = 100  # updates between hard copies to the target networks
    grad_clip_norm: float = 40.0  # global norm, per network
    exploration_sigma: float = 0.3  # Gaussian noise std as a fraction of each action's half-range
    replay_min_size: int = 2000
    replay_max_size: int = 200_000
    samples_per_insert: float = 64.0  # items sampled per item inserted: batch 256 every 4 env steps
    samples_per_insert_tolerance: float = 0.1  # error buffer = tolerance * min_size * spi (at least a batch)
    prioritized: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        if self.encoder not in ("pooled", "conv"):
            raise ValueError(f"encoder must be 'pooled' or 'conv', got {self.encoder!r}")
        if self.atoms < 2 or not self.v_min < self.v_max:
            raise ValueError("need atoms >= 2 and v_min < v_max")
        if not 0 < self.discount <= 1 or self.n_step < 1 or self.batch_size < 1:
            raise ValueError("need 0 < discount <= 1, n_step >= 1, batch_size >= 1")
        for name in ("actor_lr", "critic_lr", "grad_clip_norm", "samples_per_insert", "pool",
                     "target_update_period", "replay_min_size", "replay_max_size"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be positive, got {value!r}")
        if self.replay_min_size > self.replay_max_size:
            raise ValueError("replay_min_size must not exceed replay_max_size")
        if any(h < 1 for h in self.hidden):
            raise ValueError("hidden widths must be positive")

    @property
    def error_buffer(self) -> float:
        """Rate-limiter slack in items; wide enough that inserts and samples never both block."""
        buffer = self.samples_per_insert_tolerance * self.replay_min_size * self.samples_per_insert
        return max(buffer, self.batch_size + self.samples_per_insert)

    @staticmethod
    def default(**changes: Any) -> "D4PGConfig":
        return dataclasses.replace(D4PGConfig(), **changes)

    @staticmethod
    def paper(**changes: Any) -> "D4PGConfig":
        """The authors' network and settings: Conv1D trunk, 512-512-256-256 ELU heads,
        51 atoms on [-40, 130] as published (we keep our wider support since the goal reward is
        +200), batch 512, 10k warm-up, sigma 1.0 clipped."""
        base = D4PGConfig(preset="paper", encoder="conv", hidden=(512, 512, 256, 256), batch_size=512,
                          replay_min_size=10_000, exploration_sigma=1.0, samples_per_insert=64.0)
        return dataclasses.replace(base, **changes)

    @staticmethod
    def named(preset: str, **changes: Any) -> "D4PGConfig":
        if preset == "default":
            return D4PGConfig.default(**changes)
        if preset == "paper":
            return D4PGConfig.paper(**changes)
        raise ValueError(f"unknown preset {preset!r}; choose 'default' or 'paper'")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["hidden"] = list(self.hidden)
        return d

    @staticmethod
    def from_dict(d: dict) -> "D4PGConfig":
        d = dict(d)
        d["hidden"] = tuple(d.get("hidden", (256, 256)))
        known = {f.name for f in dataclasses.fields(D4PGConfig)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown D4PG config keys {sorted(unknown)}")
        return D4PGConfig(**d)
