"""One bus identity per actor replica (issue 30): replicas that cannot be told apart (compose
``--scale``) each claim a different ``actor-<n>`` and authenticate as it; a dead replica's
identity is free again; when every identity is held the replica stops with one line that says
what to do. No Docker: processes racing on one folder, as replicas race on the ``bus-actors``
volume. Compose itself: ``tests/test_deploy_containers.py`` (distinct identities of live replicas, no
shared actor user)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from curlnav.bus import identity
from curlnav.bus.identity import IdentitiesExhausted, actor_identities, claim_actor_identity
from curlnav.bus.security import SHARED_ACTOR, BusCredentialsError, make_credentials
from curlnav.run.launch import _actor_identity

ROOT = Path(__file__).resolve().parent.parent
RUN = "compose"

CLAIMER = textwrap.dedent("""
    import sys
    from curlnav.bus.identity import claim_actor_identity
    try:
        claim = claim_actor_identity(sys.argv[1])
    except Exception as exc:
        print("refused:", exc, flush=True)
        sys.exit(2)
    print("claimed", claim.name, flush=True)
    sys.stdin.read()  # hold it until told to go
""")


class Replicas:
    """Processes that each claim an identity of ``folder`` at once, as replicas starting together."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.procs: list[subprocess.Popen] = []

    def start(self, count: int) -> list[str]:
        """Start ``count`` claimers together; their first lines, in start order."""
        new = [subprocess.Popen([sys.executable, "-c", CLAIMER, str(self.folder)], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, text=True, cwd=ROOT) for _ in range(count)]
        self.procs += new
        return [p.stdout.readline().strip() for p in new]

    def close(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.kill()
            p.wait(10)


@pytest.fixture(autouse=True)
def release_claims():
    """Identities this test process claimed are given back after each test."""
    yield
    for claim in list(identity._HELD.values()):
        claim.release()


@pytest.fixture
def replicas(tmp_path):
    r = Replicas(tmp_path / "bus")
    make_credentials(r.folder, RUN, actors=4)
    try:
        yield r
    finally:
        r.close()


@pytest.mark.slow
def test_replicas_starting_together_claim_distinct_identities_and_the_rest_stop_with_one_line(replicas):
    lines = replicas.start(6)
    claimed = sorted(line.split()[1] for line in lines if line.startswith("claimed"))
    refusers = [p for p, line in zip(replicas.procs, lines, strict=True) if line.startswith("refused")]
    assert claimed == ["actor-0", "actor-1", "actor-2", "actor-3"], lines
    assert [p.wait(30) for p in refusers] == [2, 2], lines
    assert all("all 4 actor identities are in use; raise CURLNAV_MAX_ACTORS and re-run the credentials service"
               in line for line in lines if line.startswith("refused")), lines


@pytest.mark.slow
def test_a_dead_replicas_identity_is_taken_by_the_next_one(replicas):
    lines = replicas.start(4)
    assert sorted(lines) == [f"claimed actor-{n}" for n in range(4)]
    assert replicas.start(1)[0].startswith("refused: all 4 actor identities are in use")
    holder = replicas.procs[lines.index("claimed actor-2")]
    os.kill(holder.pid, signal.SIGKILL)  # no clean-up runs: the kernel drops the lock
    holder.wait(10)
    assert replicas.start(1) == ["claimed actor-2"]


def test_an_identity_is_held_until_released_in_one_process(tmp_path):
    make_credentials(tmp_path, RUN, actors=2)
    first, second = claim_actor_identity(tmp_path), claim_actor_identity(tmp_path)
    try:
        assert (first.name, first.index, second.name) == ("actor-0", 0, "actor-1")
        with pytest.raises(IdentitiesExhausted, match="all 2 actor identities are in use"):
            claim_actor_identity(tmp_path)
        first.release()
        again = claim_actor_identity(tmp_path)
        assert again.name == "actor-0"
        again.release()
    finally:
        first.release()
        second.release()


def test_a_swarm_slot_names_its_identity(tmp_path):
    make_credentials(tmp_path, RUN, actors=3)
    claim = claim_actor_identity(tmp_path, slot=2)  # Swarm's {{.Task.Slot}} counts from 1
    try:
        assert claim.name == "actor-1"
        with pytest.raises(IdentitiesExhausted, match=r"actor identity actor-1 \(slot 2\) is in use"):
            claim_actor_identity(tmp_path, slot=2)
        with pytest.raises(IdentitiesExhausted, match="actor slot 4 has no identity: 3 actor identities are minted"):
            claim_actor_identity(tmp_path, slot=4)
    finally:
        claim.release()
    with pytest.raises(BusCredentialsError, match="no actor identities"):
        claim_actor_identity(tmp_path / "router")


def identity_args(credentials: Path | str = "", actor_id: str = "", slot: int = 0) -> SimpleNamespace:
    return SimpleNamespace(actor_id=actor_id, bus_credentials=str(credentials) if credentials else "", actor_slot=slot)


def test_serve_actor_claims_an_identity_from_a_folder_of_them_and_keeps_the_old_ways(tmp_path):
    """``curlnav serve actor`` without --actor-id: a claimed identity (the compose replicas'), the
    one actor of a single actor's folder, or host-pid with the shared actor user (``--shared-actor``)."""
    pool, shared = tmp_path / "pool", tmp_path / "shared"
    make_credentials(pool, RUN, actors=2)
    assert _actor_identity(identity_args(pool)) == ("actor-0", 0)
    with pytest.raises(IdentitiesExhausted, match=r"actor identity actor-0 \(slot 1\) is in use"):
        _actor_identity(identity_args(pool, slot=1))
    assert _actor_identity(identity_args(pool, slot=2)) == ("actor-1", 1)
    with pytest.raises(IdentitiesExhausted, match="all 2 actor identities are in use"):
        _actor_identity(identity_args(pool))
    assert _actor_identity(identity_args(pool / "actor-1")) == ("actor-1", None)  # its own folder: no claim
    assert _actor_identity(identity_args(pool, actor_id="actor-7")) == ("actor-7", None)
    make_credentials(shared, RUN, actors=0, shared_actor=True)  # an old compose volume: the shared user only
    assert actor_identities(shared) == []
    ident, index = _actor_identity(identity_args(shared / SHARED_ACTOR))
    assert index is None and re.fullmatch(r".+-\d+", ident) and not ident.startswith("actor-")


@pytest.mark.slow
def test_the_compose_file_mints_an_identity_per_replica_and_no_shared_actor_user(tmp_path):
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    credentials, actor = compose["services"]["credentials"], compose["services"]["actor"]
    command = credentials["entrypoint"][-1]
    assert "--shared-actor" not in command and "bus-actor:" not in str(compose)
    assert "bus-actors:/bus" in credentials["volumes"] and "bus-actors:/bus:ro" in actor["volumes"]
    assert actor["environment"]["CURLNAV_BUS_CREDENTIALS"] == "/bus" and "CURLNAV_ACTOR_ID" not in actor["environment"]
    # the credentials service's own command line, with its default CURLNAV_MAX_ACTORS
    cli = command.split("&&")[0].split()
    assert cli[:3] == ["curlnav", "bus", "credentials"]
    max_actors = re.fullmatch(r"\$\{CURLNAV_MAX_ACTORS:-(\d+)\}", credentials["environment"]["CURLNAV_MAX_ACTORS"])
    env = {**os.environ, "CURLNAV_MAX_ACTORS": max_actors.group(1), "CURLNAV_RUN": RUN}
    out = tmp_path / "bus"
    args = [a.replace("/bus", str(out)) for a in cli[3:]]
    result = subprocess.run([sys.executable, "-m", "curlnav.cli", "bus", "credentials", *args], env=env,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert actor_identities(out) == [f"actor-{n}" for n in range(int(max_actors.group(1)))]
    users = [line.split(":", 1)[0] for line in (out / "router" / "users.txt").read_text().splitlines()]
    assert SHARED_ACTOR not in users and not (out / SHARED_ACTOR).exists()


@pytest.mark.slow
def test_a_replica_beyond_the_identities_stops_with_one_line_and_exit_2(tmp_path):
    make_credentials(tmp_path, RUN, actors=1)
    held = claim_actor_identity(tmp_path)  # the one replica there is
    result = subprocess.run([sys.executable, "-m", "curlnav.cli", "serve", "actor", "--run", RUN, "--bus-credentials",
                             str(tmp_path), "--router-timeout-s", "1"], capture_output=True, text=True, timeout=120)
    held.release()
    assert result.returncode == 2, result.stderr[-2000:]
    assert result.stderr.strip().splitlines() == [
        "curlnav: error: all 1 actor identities are in use; raise CURLNAV_MAX_ACTORS and re-run the credentials "
        "service (or `curlnav bus credentials --actors N`)"]
