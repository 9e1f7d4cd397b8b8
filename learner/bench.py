"""``curlnav bench learner``: D4PG updates per second for each preset on this machine."""

from __future__ import annotations

import dataclasses
import os
import platform
import time

import torch

from curlnav.config import ExperimentConfig
from curlnav.layout import ObservationLayout

from .d4pg import TensorBatch, init_state, sgd_step


def updates_per_second(preset: str, seconds: float, batch_size: int, device: str | None = None) -> tuple[float, int]:
    cfg = dataclasses.replace(ExperimentConfig.preset(preset).d4pg, batch_size=batch_size)
    layout = ObservationLayout()
    state = init_state(cfg, layout, device)
    dev = state.device
    g = torch.Generator().manual_seed(0)
    b = batch_size
    batch = TensorBatch((torch.rand(b, layout.size, generator=g) * 5).to(dev), torch.rand(b, 3, generator=g).to(dev),
                        torch.randn(b, generator=g).to(dev), torch.full((b,), 0.95).to(dev),
                        (torch.rand(b, layout.size, generator=g) * 5).to(dev))
    sgd_step(state, batch)  # warm-up
    n = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        sgd_step(state, batch)
        n += 1
    if dev.type == "cuda":
        torch.cuda.synchronize()
    return n / (time.perf_counter() - t0), sum(p.numel() for p in state.actor.parameters()) + sum(
        p.numel() for p in state.critic.parameters())


def run_learner_bench(presets: list[str], seconds: float = 20.0, batch_size: int = 256, threads: int = 2) -> dict:
    torch.set_num_threads(threads)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    print(f"machine: {platform.machine()} cpus={os.cpu_count()} torch={torch.__version__} device={device} "
          f"threads={threads} batch={batch_size}")
    out = {}
    for preset in presets:
        rate, params = updates_per_second(preset, seconds, batch_size)
        out[preset] = rate
        print(f"{preset:8s} {rate:8.1f} updates/s  ({params / 1e6:.2f} M parameters in actor + critic, "
              f"{rate * batch_size:,.0f} sampled transitions/s)")
    return out
