"""Command-line access to the experiment config, shared by ``curlnav train``, ``curlnav serve``
and ``curlnav config show``: ``--preset``, ``--config FILE``, ``--set section.field=value``
(repeatable), ``CURLNAV_<SECTION>__<FIELD>`` variables, and the short options of ``train``
(each one is an alias of a config field, listed in ``OPTION_FIELDS``).

Precedence, later wins: preset, file, ``CURLNAV_*`` variables, short options, ``--set``.
"""

from __future__ import annotations

import argparse
import os

from curlnav.config import PRESETS, ExperimentConfig, resolve_config

#: train's short options and the config field each one sets
OPTION_FIELDS = {
    "world": "curriculum.world",
    "curriculum": "curriculum.file",
    "minutes": "budget.minutes",
    "max_env_steps": "budget.max_env_steps",
    "warmup_steps": "exploration.warmup_steps",
    "eval_every_s": "evaluation.every_s",
    "eval_episodes": "evaluation.episodes",
    "stop_at_success": "evaluation.stop_at_success",
    "seed": "seed",
    "robot": "robot",
    "init_from": "init_from",  # train's --init-from (curlnav/run/commands.py)
}


def add_config_arguments(p: argparse.ArgumentParser) -> None:
    """``--preset``, ``--config``, ``--set`` (every command that runs an experiment)."""
    p.add_argument("--preset", default=None, choices=sorted(PRESETS),
                   help="preset to start from (default: default; CURLNAV_PRESET)")
    p.add_argument("--config", default=None,
                   help="experiment YAML: any subset of the fields of `curlnav config show` (CURLNAV_CONFIG)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="override one config field, e.g. --set d4pg.batch_size=512 (repeatable)")


def add_train_options(p: argparse.ArgumentParser) -> None:
    """The short options of ``train``; each is an alias of a config field (default: the config's)."""
    p.add_argument("--world", default=None,
                   help="world to train on: built-in name, world YAML, or FAMILY:SEED for a generated world, "
                        "e.g. t-maze:0 (curriculum.world)")
    p.add_argument("--curriculum", default=None, help="curriculum YAML (curriculum.file)")
    p.add_argument("--minutes", type=float, default=None, help="wall-clock budget (budget.minutes; default 15)")
    p.add_argument("--max-env-steps", type=int, default=None, help="environment step budget (budget.max_env_steps)")
    p.add_argument("--warmup-steps", type=int, default=None,
                   help="random-action steps at the start, shared by the actors (exploration.warmup_steps; default 2000)")
    p.add_argument("--eval-every-s", type=float, default=None, help="s between held-out evaluations (evaluation.every_s)")
    p.add_argument("--eval-episodes", type=int, default=None, help="held-out pairs per evaluation (evaluation.episodes)")
    p.add_argument("--stop-at-success", type=float, default=None,
                   help="stop when a held-out evaluation reaches this rate (evaluation.stop_at_success)")
    p.add_argument("--seed", type=int, default=None, help="experiment seed (seed)")
    p.add_argument("--robot", default=None, metavar="PROFILE",
                   help="robot profile: husky (default), jackal or a profile file: the base, arm and LiDAR "
                        "(robot; docs/guide/robots.md)")


def option_overrides(args: argparse.Namespace) -> list[str]:
    """The short options the user gave, as ``field=value`` overrides."""
    out = []
    for option, path in OPTION_FIELDS.items():
        value = getattr(args, option, None)
        if value is not None:
            out.append(f"{path}={value}" if not isinstance(value, str) else f"{path}={_yaml_string(value)}")
    return out


def _yaml_string(value: str) -> str:
    return "''" if value == "" else repr(value) if any(c in value for c in ":#{}[],&*!|>'\"%@`") else value


def experiment_from_args(args: argparse.Namespace, environ: dict[str, str] | None = None) -> ExperimentConfig:
    """Preset, ``--config``, ``CURLNAV_*`` variables, short options, ``--set``: the resolved config."""
    environ = os.environ if environ is None else environ
    preset = args.preset or environ.get("CURLNAV_PRESET") or None
    config = args.config or environ.get("CURLNAV_CONFIG") or None
    return resolve_config(config, preset, option_overrides(args) + list(args.overrides or []), environ)
