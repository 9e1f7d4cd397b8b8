"""D4PG: the learner's state, the categorical projection and one SGD step.

``sgd_step(state, batch) -> (state, metrics)`` is the whole algorithm; every loop (serial
trainer, learner service) is a thin shell around it. PyTorch updates the state's tensors in
place; the function still returns the state so callers read as if it were pure.
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from curlnav.config import D4PGConfig
from curlnav.layout import ObservationLayout

from .networks import ACTION_HIGH, ACTION_LOW, Actor, DistributionalCritic, act, check_network_size  # noqa: F401  (act: re-exported)


def categorical_projection(next_probs: torch.Tensor, reward: torch.Tensor, discount: torch.Tensor,
                           support: torch.Tensor) -> torch.Tensor:
    """Project the distribution of ``reward + discount * Z'`` onto ``support``.

    ``next_probs`` (B, K) are the probabilities of Z' on ``support`` (K,), evenly spaced;
    ``reward`` and ``discount`` are (B,) (the n-step return and gamma^m, 0 at a terminal).
    Each shifted atom's mass is split between its two neighbouring atoms in proportion to
    closeness (atoms beyond the ends are clipped onto them). Returns (B, K), rows summing to 1.
    """
    k = support.shape[0]
    v_min, v_max = support[0], support[-1]
    delta = (v_max - v_min) / (k - 1)
    shifted = (reward[:, None] + discount[:, None] * support[None, :]).clamp(v_min, v_max)  # (B, K)
    position = (shifted - v_min) / delta  # fractional index of each shifted atom
    lower = position.floor().clamp(0, k - 1)
    upper_weight = position - lower  # share of mass for the atom above
    lower = lower.long()
    upper = (lower + 1).clamp(max=k - 1)
    out = torch.zeros_like(next_probs)
    out.scatter_add_(1, lower, next_probs * (1.0 - upper_weight))
    out.scatter_add_(1, upper, next_probs * upper_weight)
    return out


@dataclass
class D4PGState:
    """Everything a learner needs to continue: networks, targets, optimisers, step count."""

    config: D4PGConfig
    layout: ObservationLayout
    actor: Actor
    critic: DistributionalCritic
    target_actor: Actor
    target_critic: DistributionalCritic
    actor_opt: torch.optim.Optimizer
    critic_opt: torch.optim.Optimizer
    steps: int = 0
    #: the actor is not updated while ``steps`` is below this: the critic learns alone under a fixed
    #: actor (a start from a trained actor without its critic, ``d4pg.critic_warmup_updates``)
    actor_frozen_until: int = 0
    #: the actor the run started from, frozen (``init_from`` with ``d4pg.anchor_weight`` > 0): the
    #: actor's loss keeps it near this one's actions. None: no anchor
    anchor: Actor | None = None
    #: "bf16": the forward passes under bfloat16 autocast (CUDA; the losses, softmaxes and the
    #: optimiser stay float32); "off": float32 throughout. How it trains, not what it holds: not saved.
    amp: str = "off"
    #: ``torch.compile``d callables of the four networks (same parameters), or None: eager
    compiled: dict | None = None

    @property
    def device(self) -> torch.device:
        return next(self.actor.parameters()).device

    def net(self, name: str):
        """The network ``name`` as called in an update: compiled when ``compile_networks`` ran."""
        return self.compiled[name] if self.compiled else getattr(self, name)


AMP_MODES = ("off", "bf16")
COMPILE_MODES = ("off", "default", "reduce-overhead", "max-autotune-no-cudagraphs")


def compile_networks(state: D4PGState, mode: str = "default") -> D4PGState:
    """Have ``sgd_step`` call ``torch.compile``d networks (``mode`` one of ``COMPILE_MODES``;
    ``off``: eager). The modules, their parameters and checkpoints are unchanged."""
    if mode not in COMPILE_MODES:
        raise ValueError(f"compile mode {mode!r}: one of {', '.join(COMPILE_MODES)}")
    state.compiled = None if mode == "off" else {
        name: torch.compile(getattr(state, name), mode=mode) for name in ("actor", "critic", "target_actor", "target_critic")}
    return state


def set_amp(state: D4PGState, amp: str) -> D4PGState:
    """``amp`` one of ``AMP_MODES``; bf16 needs a device with bfloat16 kernels (any CUDA GPU
    since Ampere runs them natively; on CPU it runs, usually slower)."""
    if amp not in AMP_MODES:
        raise ValueError(f"amp {amp!r}: one of {', '.join(AMP_MODES)}")
    state.amp = amp
    return state


def default_device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def init_state(config: D4PGConfig, layout: ObservationLayout, device: torch.device | str | None = None) -> D4PGState:
    check_network_size(layout, config)  # before anything is allocated
    torch.manual_seed(config.seed)
    device = torch.device(device) if device is not None else default_device()
    actor = Actor(layout, config).to(device)
    critic = DistributionalCritic(layout, config).to(device)
    target_actor = copy.deepcopy(actor).requires_grad_(False)
    target_critic = copy.deepcopy(critic).requires_grad_(False)
    fused = device.type == "cuda"  # one kernel for all parameters instead of several per tensor
    return D4PGState(config, layout, actor, critic, target_actor, target_critic,
                     torch.optim.Adam(actor.parameters(), lr=config.actor_lr, fused=fused),
                     torch.optim.Adam(critic.parameters(), lr=config.critic_lr, fused=fused))


def anchored_copy(actor: Actor) -> Actor:
    """A frozen copy of ``actor``: a fine-tuning run's anchor (``D4PGState.anchor``)."""
    return copy.deepcopy(actor).requires_grad_(False).eval()


# The D4PG fields that shape the networks' weights (encoder, widths, the return support): a
# checkpoint's weights fit another config only if these agree. The others (n-step length,
# discount, batch size, learning rates, target period, clipping, seed) are how it trains.
NETWORK_FIELDS = ("encoder", "pool", "conv_filters", "hidden", "atoms", "v_min", "v_max")


def network_differences(a: D4PGConfig, b: D4PGConfig) -> list[str]:
    """The network-shaping fields where ``a`` and ``b`` differ, as ``field a vs b``."""
    return [f"d4pg.{k} {getattr(a, k)!r} vs {getattr(b, k)!r}" for k in NETWORK_FIELDS if getattr(a, k) != getattr(b, k)]


def adopt_training_config(state: D4PGState, config: D4PGConfig) -> list[str]:
    """Continue ``state``'s networks and optimiser moments under ``config``'s training settings
    (fine-tuning with another n-step length, batch size or learning rate). The networks must be
    the same shape (``network_differences`` empty). Returns the training fields that changed."""
    differences = network_differences(state.config, config)
    if differences:
        raise ValueError("the networks differ: " + "; ".join(differences))
    changed = [f"d4pg.{k} {getattr(state.config, k)!r} -> {getattr(config, k)!r}"
               for k in config.__dataclass_fields__ if k not in NETWORK_FIELDS + ("preset",)
               and getattr(state.config, k) != getattr(config, k)]
    for opt, lr in ((state.actor_opt, config.actor_lr), (state.critic_opt, config.critic_lr)):
        for group in opt.param_groups:
            group["lr"] = lr
    state.config = config
    return changed


@dataclass
class TensorBatch:
    obs: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    discount: torch.Tensor
    next_obs: torch.Tensor
    weights: torch.Tensor | None = None  # importance weights for prioritised replay

    @staticmethod
    def from_sample(sample, device: torch.device, weights: np.ndarray | None = None) -> TensorBatch:
        def t(x):
            return torch.tensor(x, dtype=torch.float32, device=device)  # a copy: decoded arrays are read-only

        return TensorBatch(t(sample.obs), t(sample.action), t(sample.reward), t(sample.discount), t(sample.next_obs),
                           None if weights is None else t(weights))


def sgd_step(state: D4PGState, batch: TensorBatch, sync: bool = True) -> tuple[D4PGState, dict, np.ndarray]:
    """One critic and one actor update (the critic's alone while ``steps < actor_frozen_until``).
    Returns (state, metrics, per-item critic loss).

    ``sync`` False: the metrics are 0-d tensors and the per-item loss a tensor, all still on the
    device, so the update itself never waits for a GPU; read them (``read_metrics``, ``.cpu()``)
    only when needed (a prioritized replay needs the per-item losses of every update).
    True: floats and a numpy array (one wait for the device per update)."""
    cfg = state.config
    critic, actor = state.critic, state.actor
    run_critic, run_actor = state.net("critic"), state.net("actor")
    support = critic.support
    amp = torch.autocast(state.device.type, dtype=torch.bfloat16, enabled=state.amp == "bf16")
    metrics_extra: dict = {}
    with torch.no_grad(), amp:
        next_action = state.net("target_actor")(batch.next_obs)
        next_logits = state.net("target_critic")(batch.next_obs, next_action)
    with torch.no_grad():
        next_probs = torch.softmax(next_logits.float(), dim=-1)
        target = categorical_projection(next_probs, batch.reward, batch.discount, support)

    with amp:
        logits = run_critic(batch.obs, batch.action)
    item_loss = -(target * torch.log_softmax(logits.float(), dim=-1)).sum(-1)
    critic_loss = (item_loss * batch.weights).mean() if batch.weights is not None else item_loss.mean()
    state.critic_opt.zero_grad(set_to_none=True)
    critic_loss.backward()
    critic_norm = torch.nn.utils.clip_grad_norm_(critic.parameters(), cfg.grad_clip_norm)
    state.critic_opt.step()

    if state.steps < state.actor_frozen_until:  # a fresh critic must first learn the trained actor's values
        with torch.no_grad(), amp:
            q = critic.mean(run_critic(batch.obs, run_actor(batch.obs)).float())
        actor_loss = -q.mean()
        actor_norm = torch.zeros((), device=q.device)
    else:
        critic.requires_grad_(False)  # the actor's gradient flows through the critic, not into it
        penalty = cfg.actor_saturation_penalty
        with amp:
            if penalty > 0:  # eager: the pre-tanh output is needed too
                pre = actor.preactivation(batch.obs)
                action = actor.squash(pre)
            else:
                action = run_actor(batch.obs)
            q_logits = run_critic(batch.obs, action)
        q = critic.mean(q_logits.float())
        actor_loss = -q.mean()
        if penalty > 0:
            actor_loss = actor_loss + penalty * pre.float().pow(2).mean()
        if state.anchor is not None and cfg.anchor_weight > 0:  # fine-tuning: stay near the starting actor
            with torch.no_grad(), amp:
                anchored = state.anchor(batch.obs)
            drift = (action.float() - anchored.float()).pow(2).sum(-1).mean()
            actor_loss = actor_loss / q.abs().mean().detach().clamp_min(1e-6) + cfg.anchor_weight * drift
            metrics_extra["losses/anchor_drift"] = drift.detach()
        state.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        actor_norm = torch.nn.utils.clip_grad_norm_(actor.parameters(), cfg.grad_clip_norm)
        state.actor_opt.step()
        critic.requires_grad_(True)

    state.steps += 1
    if state.steps % cfg.target_update_period == 0:
        state.target_actor.load_state_dict(actor.state_dict())
        state.target_critic.load_state_dict(critic.state_dict())
    metrics = {"losses/critic": critic_loss.detach(), "losses/actor": actor_loss.detach(), "values/q_mean": q.mean().detach(),
               "grads/critic_norm": critic_norm.detach(), "grads/actor_norm": actor_norm.detach(), **metrics_extra}
    if not sync:
        return state, metrics, item_loss.detach()
    return state, read_metrics(metrics), item_loss.detach().cpu().numpy()


def read_metrics(metrics: dict) -> dict[str, float]:
    """``sgd_step``'s metrics as floats (one wait for the device when they are tensors)."""
    if not metrics or not isinstance(next(iter(metrics.values())), torch.Tensor):
        return dict(metrics)
    values = torch.stack([v.float() for v in metrics.values()]).cpu().tolist()
    return dict(zip(metrics, values))


# -- checkpoints (safetensors + JSON, no pickle) -----------------------------------------------
def _flatten_optimizer(prefix: str, opt: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict]:
    sd = opt.state_dict()
    tensors = {}
    for index, param_state in sd["state"].items():
        for key, value in param_state.items():
            tensors[f"{prefix}.state.{index}.{key}"] = torch.as_tensor(value).detach().cpu().contiguous()
    return tensors, {"param_groups": sd["param_groups"]}


def _unflatten_optimizer(prefix: str, tensors: dict[str, torch.Tensor], groups: dict) -> dict:
    state: dict[int, dict] = {}
    for name, value in tensors.items():
        if not name.startswith(prefix + ".state."):
            continue
        index, key = name[len(prefix) + 7:].split(".", 1)
        state.setdefault(int(index), {})[key] = value
    return {"state": state, "param_groups": groups["param_groups"]}


def save_checkpoint(state: D4PGState, path: str | Path, extra: dict | None = None) -> Path:
    """Write networks, targets, optimiser moments (and a fine-tuning run's anchor) to one safetensors
    file, with JSON metadata."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors: dict[str, torch.Tensor] = {}
    for name in ("actor", "critic", "target_actor", "target_critic") + (("anchor",) if state.anchor is not None else ()):
        for key, value in getattr(state, name).state_dict().items():
            tensors[f"{name}.{key}"] = value.detach().cpu().contiguous()
    actor_opt, actor_groups = _flatten_optimizer("actor_opt", state.actor_opt)
    critic_opt, critic_groups = _flatten_optimizer("critic_opt", state.critic_opt)
    tensors.update(actor_opt)
    tensors.update(critic_opt)
    meta = {"format": "curlnav-d4pg-checkpoint", "version": 1, "steps": state.steps,
            "actor_frozen_until": state.actor_frozen_until,
            "config": state.config.to_dict(), "layout": state.layout.to_dict(),
            "actor_opt": actor_groups, "critic_opt": critic_groups, "extra": extra or {}}
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata={"curlnav": json.dumps(meta)})
    tmp.replace(path)
    return path


def check_resumed_layout(state: D4PGState, layout: ObservationLayout, path: str | Path, folder: str) -> None:
    """Refuse (``ConfigError``, one line) to resume the checkpoint at ``path`` into a run that reads
    another observation ``layout`` (another LiDAR or frame count, or a memory toggled): its
    networks would meet observations of another size at the first update."""
    if state.layout != layout:
        from curlnav.config import ConfigError

        raise ConfigError(f"{path} was trained on another observation ({state.layout.to_dict()}, this run reads "
                          f"{layout.to_dict()}): use the run's config, or another {folder}")


def load_checkpoint(path: str | Path, device: torch.device | str | None = None) -> tuple[D4PGState, dict]:
    """Rebuild a ``D4PGState`` from ``save_checkpoint``'s file; returns (state, extra)."""
    from safetensors import safe_open

    path = Path(path)
    with safe_open(str(path), framework="pt") as f:
        meta = json.loads(f.metadata()["curlnav"])
    if meta.get("format") != "curlnav-d4pg-checkpoint":
        raise ValueError(f"{path}: not a curlnav D4PG checkpoint")
    try:  # every size checked (config bounds, layout bounds, parameters) before a tensor is read or made
        config, layout = D4PGConfig.from_dict(meta["config"]), ObservationLayout(**meta["layout"])
        check_network_size(layout, config)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: {exc}") from None
    tensors = load_file(str(path))
    state = init_state(config, layout, device)
    for key in ("actor_opt", "critic_opt"):  # fused Adam on the device it resumes on, wherever it was saved
        for group in meta[key]["param_groups"]:
            group["fused"] = state.device.type == "cuda"
            group["foreach"] = None
    for name in ("actor", "critic", "target_actor", "target_critic"):
        module = getattr(state, name)
        module.load_state_dict({k[len(name) + 1:]: v for k, v in tensors.items() if k.startswith(name + ".")})
    state.actor_opt.load_state_dict(_unflatten_optimizer("actor_opt", tensors, meta["actor_opt"]))
    state.critic_opt.load_state_dict(_unflatten_optimizer("critic_opt", tensors, meta["critic_opt"]))
    state.steps = int(meta["steps"])
    state.actor_frozen_until = int(meta.get("actor_frozen_until", 0))  # a learner restarted during the critic's warm-up
    anchor = {k[len("anchor."):]: v for k, v in tensors.items() if k.startswith("anchor.")}
    if anchor:  # a fine-tuning run's starting actor (d4pg.anchor_weight)
        state.anchor = anchored_copy(state.actor)
        state.anchor.load_state_dict(anchor)
    return state, meta.get("extra", {})
