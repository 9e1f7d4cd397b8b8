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


class CommentDocstrings(griffe.Extension):
    """Fields documented the way this code base documents them, with a comment (``n_step: int = 5
    # steps per n-step return``, or comment lines just above), get that comment as their docstring,
    so the reference shows every config field with its unit."""

    def on_attribute_instance(self, *, attr: griffe.Attribute, **kwargs) -> None:
        if attr.docstring is not None or not attr.lineno or attr.filepath is None or isinstance(attr.filepath, list):
            return
        lines = attr.lines_collection[attr.filepath] if attr.filepath in attr.lines_collection else []
        if not lines or attr.lineno > len(lines):
            return
        first = lines[attr.lineno - 1]
        comment = ""
        if "  # " in first:
            comment = first.split("  # ", 1)[1].strip()
        else:
            above = []
            i = attr.lineno - 2
            while i >= 0 and lines[i].strip().startswith("#"):
                above.insert(0, lines[i].strip().lstrip("#").strip())
                i -= 1
            comment = " ".join(above)
        if comment:
            attr.docstring = griffe.Docstring(comment, lineno=attr.lineno, parent=attr)
