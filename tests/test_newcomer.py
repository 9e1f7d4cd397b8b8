"""What a newcomer trips on, typed as printed: hints that run without an activated virtual
environment, a resume that goes on from its counts, the best policy that also avoids walls,
``curlnav status`` on a finished run, one form for every world argument, labelled config hashes."""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _first_word_runs(line: str) -> list[str]:
    words = shlex.split(line)
    program = words[0]
    assert os.path.isabs(program), f"{line!r}: {program} is looked up on PATH (no venv there)"
    assert os.path.isfile(program) and os.access(program, os.X_OK), f"{line!r}: {program} is not an executable"
    return words


def test_the_launchers_hints_run_as_printed_without_an_activated_virtual_environment(tmp_path):
    from curlnav.run.supervise import start_hints

    lines = start_hints(tmp_path / "run", "http://127.0.0.1:1/status", "http://127.0.0.1:2")
    hints = [line.split("(", 1)[1].rsplit(")", 1)[0] if "(" in line else line.split(":", 1)[1] for line in lines]
    commands = [_first_word_runs(h) for h in hints]
    assert [Path(c[0]).name for c in commands] == ["curlnav", "curlnav", "tensorboard"]
    assert commands[0][1:] == ["status", str(tmp_path / "run")]
    assert commands[1][1:] == ["pull", "--from", "http://127.0.0.1:2"]
    assert commands[2][1:] == ["--logdir", str(tmp_path / "run" / "tensorboard")]
    # typed in a shell whose PATH has no venv: curlnav answers (not "command not found")
    bare = {"PATH": "/usr/bin:/bin", "HOME": os.environ.get("HOME", "/tmp")}
    status = subprocess.run([*commands[0][:1], "--version"], capture_output=True, text=True, env=bare, timeout=120)
    assert status.returncode == 0 and status.stdout.startswith("curlnav"), status.stderr
    assert shutil.which(commands[2][0]) == commands[2][0]


def test_hints_fall_back_to_python_dash_m_where_no_console_script_is_beside_the_interpreter(tmp_path, monkeypatch):
    from curlnav.run.launch import shell_command

    fake = tmp_path / "bin" / "python"
    fake.parent.mkdir()
    fake.symlink_to(os.path.realpath(sys.executable))
    monkeypatch.setattr(sys, "executable", str(fake))
    words = _first_word_runs(shell_command("curlnav", "status", "runs/x"))
    assert words[1:] == ["-m", "curlnav.cli", "status", "runs/x"]
