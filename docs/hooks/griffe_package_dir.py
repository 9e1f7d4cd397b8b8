"""Griffe extension for the API reference: the service folders as subpackages of ``curlnav``.

pyproject's ``[tool.setuptools.package-dir]`` makes ``replay/`` the package ``curlnav.replay``
(and likewise ``actor/``, ``learner/``, ``proto/``, ``scheduler/``). Python finds them through the
editable install's finder, but griffe reads the source tree and sees only ``curlnav/``, so
``::: curlnav.replay.ReplayTable`` would not be found. When griffe has loaded ``curlnav``, this loads
each mapped folder under it, read from pyproject so the two never disagree.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import griffe

ROOT = Path(__file__).resolve().parents[2]


def mapped_packages(root: Path = ROOT) -> dict[str, Path]:
    """``{"curlnav.replay": <root>/replay, ...}`` from pyproject's package-dir table."""
    tool = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    return {name: root / folder for name, folder in tool.get("package-dir", {}).items() if "." in name}


class PackageDir(griffe.Extension):
    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs) -> None:
        for name, folder in mapped_packages().items():
            parent, _, child = name.rpartition(".")
            if parent != pkg.path or child in pkg.members:
                continue
            # griffe has no public call to load a folder as a submodule of a loaded package
            sub = loader._load_module(child, folder / "__init__.py", submodules=True, parent=pkg)
            pkg.set_member(child, sub)
