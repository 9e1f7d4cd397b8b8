"""``curlnav bench learner``: D4PG updates per second on this machine.

One row per preset and variant. A variant is how the update runs, not what it computes:

- ``eager``: the networks as written, float32, a wait for the device after every update (its
  metrics read as floats), as the serial trainer runs;
- ``async``: the same update, its metrics left on the device (``sgd_step(sync=False)``), so a GPU
  is not waited for (the learner service on CUDA);
- ``compile``: ``torch.compile`` of the four networks (mode ``default``), async;
- ``cudagraphs``: ``torch.compile`` mode ``reduce-overhead`` (CUDA graphs), async;
- ``bf16``: async under bfloat16 autocast (forward passes; losses and optimiser float32).

Each row also gives the sampled transitions/s it consumes (updates/s x batch). The batch is
fixed random data already on the device (the data path is ``curlnav bench transport``'s).

``--check-amp`` trains the same networks on the same stream of batches in float32 and in bf16
for ``--check-steps`` updates and prints both critic losses over the last 50 updates and their
relative difference: whether mixed precision keeps the losses equal.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

    from curlnav.layout import ObservationLayout
    from curlnav.learner.d4pg import TensorBatch

VARIANTS = {  # name -> (compile mode, amp, sync)
    "eager": ("off", "off", True),
    "async": ("off", "off", False),
    "compile": ("default", "off", False),
    "cudagraphs": ("reduce-overhead", "off", False),
    "bf16": ("off", "bf16", False),
    "bf16+compile": ("default", "bf16", False),
}

HELP = "D4PG learner updates/s per preset"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--presets", default="default,paper", help="comma-separated config presets")
    p.add_argument("--seconds", type=float, default=20.0, help="timed seconds per preset")
    p.add_argument("--batch", type=int, default=256, help="batch size")
    p.add_argument("--threads", type=int, default=2, help="torch threads")
    p.add_argument("--device", default=None, help="cpu, cuda or cuda:N (default: cuda when present)")
    p.add_argument("--variants", default="eager", help="how the update runs, comma-separated: eager, async, compile, "
                                                      "cudagraphs, bf16, bf16+compile (see curlnav.bench.learner)")
    p.add_argument("--check-amp", action="store_true", help="also train float32 and bf16 side by side and compare "
                                                           "their critic losses")
    p.add_argument("--check-steps", type=int, default=500, help="updates of the amp check")


def main(args: argparse.Namespace) -> int:
    run_learner_bench(presets=args.presets.split(","), seconds=args.seconds, batch_size=args.batch, threads=args.threads,
                      device=args.device, variants=args.variants.split(","), check_amp=args.check_amp,
                      check_steps=args.check_steps)
    return 0


def random_batch(layout: ObservationLayout, b: int, device: torch.device, seed: int = 0) -> TensorBatch:
    import torch

    from curlnav.learner.d4pg import TensorBatch

    g = torch.Generator().manual_seed(seed)
    return TensorBatch((torch.rand(b, layout.size, generator=g) * 5).to(device), torch.rand(b, 3, generator=g).to(device),
                       torch.randn(b, generator=g).to(device), torch.full((b,), 0.95).to(device),
                       (torch.rand(b, layout.size, generator=g) * 5).to(device))


def _sync(device: torch.device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def updates_per_second(preset: str, seconds: float, batch_size: int, device: str | None = None,
                       variant: str = "eager") -> tuple[float, int]:
    """(updates/s, parameters of actor + critic) of ``variant`` (``VARIANTS``)."""
    from curlnav.config import ExperimentConfig
    from curlnav.layout import ObservationLayout
    from curlnav.learner.d4pg import compile_networks, init_state, read_metrics, set_amp, sgd_step

    compile_mode, amp, sync = VARIANTS[variant]
    cfg = dataclasses.replace(ExperimentConfig.preset(preset).d4pg, batch_size=batch_size)
    layout = ObservationLayout()
    state = set_amp(compile_networks(init_state(cfg, layout, device), compile_mode), amp)
    dev = state.device
    batch = random_batch(layout, batch_size, dev)
    for _ in range(3 if compile_mode == "off" else 30):  # warm-up (compilation, graph capture)
        sgd_step(state, batch, sync=sync)
    _sync(dev)
    n = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(10):
            _, metrics, _ = sgd_step(state, batch, sync=sync)
        n += 10
    read_metrics(metrics)
    _sync(dev)
    return n / (time.perf_counter() - t0), sum(p.numel() for p in state.actor.parameters()) + sum(
        p.numel() for p in state.critic.parameters())


def amp_loss_check(preset: str, steps: int, batch_size: int, device: str | None = None) -> tuple[float, float, float]:
    """Critic loss, mean of the last 50 of ``steps`` updates, in float32 and in bf16 from the same
    initial networks and batches; and their relative difference."""
    import torch

    from curlnav.config import ExperimentConfig
    from curlnav.layout import ObservationLayout
    from curlnav.learner.d4pg import init_state, set_amp, sgd_step

    layout = ObservationLayout()
    cfg = dataclasses.replace(ExperimentConfig.preset(preset).d4pg, batch_size=batch_size)
    out = []
    for amp in ("off", "bf16"):
        state = set_amp(init_state(cfg, layout, device), amp)
        losses = []
        for i in range(steps):
            batch = random_batch(layout, batch_size, state.device, seed=i % 64)
            _, metrics, _ = sgd_step(state, batch, sync=False)
            losses.append(metrics["losses/critic"])
        tail = torch.stack(losses[-50:]).float().mean().item()
        out.append(tail)
    return out[0], out[1], abs(out[1] - out[0]) / max(abs(out[0]), 1e-9)


def run_learner_bench(presets: list[str], seconds: float = 20.0, batch_size: int = 256, threads: int = 2,
                      device: str | None = None, variants: list[str] | None = None, check_amp: bool = False,
                      check_steps: int = 500) -> dict:
    import torch

    torch.set_num_threads(threads)
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    variants = variants or ["eager"]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise ValueError(f"unknown variant(s) {', '.join(unknown)}: one of {', '.join(VARIANTS)}")
    name = torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else platform.processor() or "cpu"
    print(f"machine: {platform.machine()} cpus={os.cpu_count()} torch={torch.__version__} device={device} ({name}) "
          f"threads={threads} batch={batch_size}")
    out = {}
    for preset in presets:
        for variant in variants:
            try:
                rate, params = updates_per_second(preset, seconds, batch_size, device, variant)
            except Exception as exc:  # a variant this torch or device cannot run: say so, go on
                print(f"{preset:8s} {variant:13s} failed: {type(exc).__name__}: {str(exc).splitlines()[0][:160]}")
                continue
            out[(preset, variant)] = rate
            print(f"{preset:8s} {variant:13s} {rate:8.1f} updates/s  ({params / 1e6:.2f} M parameters in actor + "
                  f"critic, {rate * batch_size:,.0f} sampled transitions/s)")
        if check_amp:
            f32, bf16, rel = amp_loss_check(preset, check_steps, batch_size, device)
            print(f"{preset:8s} amp check: critic loss over updates {check_steps - 50}-{check_steps}: float32 {f32:.4f}, "
                  f"bf16 {bf16:.4f}, relative difference {rel:.2%}")
            out[(preset, "amp_check")] = rel
    return out
