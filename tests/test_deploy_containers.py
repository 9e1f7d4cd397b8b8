"""The container smoke test (scripts/compose-smoke.sh) against a real Docker engine.

Skipped, with the reason, where no engine runs; .ci/run starts one first (scripts/start-docker.sh).
"""

from __future__ import annotations

import shutil
import subprocess

import pytest

pytestmark = [pytest.mark.docker, pytest.mark.slow]


def engine_running() -> bool:
    """Whether a Docker engine answers, asked through the Docker SDK (the `docker` dependency)."""
    if shutil.which("docker") is None:
        return False
    import docker

    try:
        client = docker.from_env(timeout=30)
        try:
            return bool(client.ping())
        finally:
            client.close()
    except docker.errors.DockerException:
        return False


@pytest.mark.timeout(1500)
@pytest.mark.skipif(not engine_running(), reason="no Docker engine running (scripts/start-docker.sh starts one)")
def test_compose_smoke_train_scale_identities_status_restart_pull_and_swarm():
    result = subprocess.run(["bash", "scripts/compose-smoke.sh"], capture_output=True, text=True, timeout=1500)
    out = "\n".join(line for line in result.stdout.splitlines() if not line.startswith("WARNING: Location"))
    print(out[-20000:])
    assert result.returncode == 0, out[-6000:] + result.stderr[-3000:]
    for step in ("up with 3 actors", "one bus identity per replica", "stop one actor container", "restart the learner",
                 "pull the latest policy", "down -v", "single-node swarm", "smoke test passed"):
        assert step in out, step
    assert "reached the goal" in out or "did not reach" in out or "timed out" in out or "stopped" in out
    volumes = subprocess.run(["docker", "volume", "ls", "-q"], capture_output=True, text=True, timeout=60).stdout.split()
    assert not {"curlnav_learner", "curlnav_replay", "curlnav_scheduler"} & set(volumes), volumes  # stack rm keeps them
