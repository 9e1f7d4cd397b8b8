"""Actor and distributional critic over the paper's observation.

Both take the flat observation ``(B, layout.size)`` (see ``curlnav.layout``): scans and labels
go through an encoder, the goal history is concatenated, then an ELU MLP.
"""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from curlnav.layout import ObservationLayout

from .config import D4PGConfig

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
        if self.kind == "pooled":
            self.pad = (-b) % self.pool
            windows = (b + self.pad) // self.pool
            self.out_features = (layout.range_frames + layout.label_frames) * windows + 3 * layout.goal_frames
        else:
            channels = layout.range_frames + layout.label_frames
            self.conv = nn.Sequential(nn.Conv1d(channels, cfg.conv_filters, 3), nn.ReLU(),
                                      nn.Conv1d(cfg.conv_filters, cfg.conv_filters, 3), nn.ReLU())
            self.out_features = cfg.conv_filters * (b - 4) + 3 * layout.goal_frames

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        layout = self.layout
        bsz = obs.shape[0]
        ranges = obs[:, :self._r_end].reshape(bsz, layout.range_frames, layout.beams) / layout.max_range
        labels = obs[:, self._r_end:self._l_end].reshape(bsz, layout.label_frames, layout.beams)
        goal = obs[:, self._l_end:]
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
        squashed = torch.tanh(self.head(self.encoder(obs)))
        return self.low + (squashed + 1.0) * 0.5 * (self.high - self.low)


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
