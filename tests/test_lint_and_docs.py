"""The house a contributor works in: lint clean, and the docs site builds with every link and page."""

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_ruff_check_is_clean():
    ruff = shutil.which("ruff", path=str(Path(sys.executable).parent)) or "ruff"
    result = subprocess.run([ruff, "check", "--no-cache", "."], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.slow
def test_docs_site_builds_strictly(tmp_path):
    """The docs site (mkdocs.yml): every page in nav, every link and anchor resolving, the API
    reference rendering from the docstrings; offline, as CI runs."""
    mkdocs = Path(sys.executable).parent / "mkdocs"
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    result = subprocess.run([str(mkdocs), "build", "--strict", "--site-dir", str(tmp_path / "site")], cwd=ROOT,
                            capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stdout + result.stderr
    assert (tmp_path / "site" / "api" / "replay" / "index.html").read_text().count("ReplayTable") > 1


def test_readme_is_a_front_door():
    """At most 300 lines, and every relative link in it points at a file of the repository."""
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 300
    missing = [link for link in re.findall(r"\]\(([^)#\s]+)", text)
               if "://" not in link and not (ROOT / link).exists()]
    assert not missing, missing
