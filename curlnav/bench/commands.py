"""``curlnav bench NAME``: one sub-command per entry of ``curlnav.bench.BENCHES``."""

from __future__ import annotations

import importlib

from curlnav.bench import BENCHES


def add_commands(sub) -> None:
    """Add ``bench`` and its sub-commands, each with its module's ``HELP``, ``add_arguments`` and ``main``."""
    bench = sub.add_parser("bench", help="benchmarks that print their figures")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    for name, module_name in BENCHES.items():
        module = importlib.import_module(module_name)
        p = bench_sub.add_parser(name, help=module.HELP)
        module.add_arguments(p)
        p.set_defaults(func=module.main)
