"""The ``curlnav`` command line. Each sub-command lives in the module that owns its work."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Help that shows each option's default (unless it has none to show or says it itself)."""

    def _get_help_string(self, action):
        if action.default is None or action.default is False or action.default == "" or "default" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


class _Parser(argparse.ArgumentParser):
    """An argument parser with ``_HelpFormatter``; its sub-command parsers are of this class too.
    Options of ``type=int`` or ``type=float`` take ASCII decimal only (``curlnav.files.decimal_int``,
    ``decimal_float``): Python's own ``int("0_1")`` is 1, and it reads non-ASCII digits."""

    def __init__(self, *args, **kwargs) -> None:
        from curlnav.files import decimal_float, decimal_int

        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)
        self.register("type", int, decimal_int)  # argparse looks a type up here before calling it
        self.register("type", float, decimal_float)

    def error(self, message: str):
        """A bad command line is one ``curlnav: error:`` line and exit 2, as every other refusal."""
        self.exit(2, f"curlnav: error: {self.prog}: {' '.join(message.split())} (see {self.prog} --help)\n")


def package_version() -> str:
    """The installed distribution's version, else the one in the source tree's pyproject.toml."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("curlnav")
    except PackageNotFoundError:
        import tomllib

        pyproject = Path(__file__).resolve().parent.parent / "pyproject.toml"
        try:
            return tomllib.loads(pyproject.read_text())["project"]["version"]
        except (OSError, KeyError, tomllib.TOMLDecodeError):
            return "unknown"


def build_parser() -> argparse.ArgumentParser:
    """Every package adds its own sub-commands (its ``commands`` module), in this order."""
    from curlnav.bench.commands import add_commands as add_bench_commands
    from curlnav.bus.commands import add_commands as add_bus_commands
    from curlnav.evaluation.commands import add_commands as add_evaluation_commands
    from curlnav.evaluation.commands import add_rollout_command, add_stack_command
    from curlnav.ros2.commands import add_ros2_commands
    from curlnav.run.commands import (
        add_ablation_commands,
        add_experiment_command,
        add_service_commands,
        add_training_commands,
    )
    from curlnav.worlds.commands import add_commands as add_worlds_commands

    parser = _Parser(prog="curlnav", description=__doc__)
    parser.add_argument("--version", action="version", version=f"curlnav {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    add_training_commands(sub)  # train, config
    add_evaluation_commands(sub)  # eval, policy
    add_stack_command(sub)  # stack show
    add_service_commands(sub)  # serve, pull, status
    add_bus_commands(sub)
    add_rollout_command(sub)
    add_worlds_commands(sub)
    add_bench_commands(sub)
    add_ablation_commands(sub)
    add_experiment_command(sub)
    add_ros2_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "pair", None) is not None and str(args.pair).isascii() and str(args.pair).isdigit():
        args.pair = int(args.pair)
    from curlnav.bus.service import ConfigMismatch
    from curlnav.bus.transport import RouterUnreachable
    from curlnav.policy import ArtefactError
    from curlnav.worlds.core.world import WorldError
    from curlnav.worlds.difficulty.metrics import MetricsError

    try:
        return int(args.func(args) or 0)
    except (WorldError, KeyError, ArtefactError, MetricsError, ValueError, RouterUnreachable, ConfigMismatch) as exc:
        message = " ".join(str(exc.args[0] if exc.args else exc).split())  # one line, whatever the library said
        if len(message) > 1000:  # a user value that no loader cut short (issue 26)
            message = message[:1000] + " ..."
        print(f"curlnav: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("curlnav: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
