"""Bus identities that cannot be turned against their user (issue 35, deliverable 4).

- An explicit ``--actor-id`` (or an actor's own folder) takes the same lock as a claimed identity:
  while another process holds ``actor-0``, a second one is refused with one line (exit 2), and a
  claiming replica never takes an identity an explicit id holds.
- ``curlnav bus credentials`` accepts only ``actor-<n>`` identities (n a number) in real folders
  and regular files: a planted ``actor-$*`` never becomes an access-control rule (a real router
  refuses it, and its user puts nothing under another actor's id), and no symbolic link makes it
  read or write outside its folder.
- ``curlnav train`` (``LocalCluster``) and the hosts bench (``HostsCluster``) give each actor only
  its own identity, and no host but the main one the CA key.

Real processes are stopped whatever happens; every wait polls with a deadline."""

from __future__ import annotations

import json
import os
import socket
import stat
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import Namespaces
from conftest import stop_all as stop

from curlnav.bench.faults import poll
from curlnav.bench.netns import Hosts, unavailable
from curlnav.bus import identity
from curlnav.bus.identity import claim_actor_identity
from curlnav.bus.security import BusCredentialsError, BusUser, load_router, load_tls, load_user, make_credentials
from curlnav.bus.transport import RouterUnreachable, open_session
from curlnav.proto.topology import Topology
from curlnav.run.launch import _actor_identity, free_port

ROOT = Path(__file__).resolve().parent.parent
RUN = "identity"
TOPO = Topology(RUN)
CLI = [sys.executable, "-m", "curlnav.cli"]


@pytest.fixture(autouse=True)
def release_claims():
    """Identities this test process holds are given back after each test."""
    yield
    for claim in list(identity._HELD.values()):
        claim.release()


# -- 1. an explicit id takes the lock ----------------------------------------------------------------

HOLDER = textwrap.dedent("""
    import sys
    from types import SimpleNamespace
    from curlnav.bus.identity import claim_actor_identity
    from curlnav.run.launch import _actor_identity
    folder, actor_id = sys.argv[1], sys.argv[2]
    try:
        if actor_id == "claim":
            name = claim_actor_identity(folder).name
        else:
            name = _actor_identity(SimpleNamespace(actor_id=actor_id, bus_credentials=folder, actor_slot=0))[0]
    except Exception as exc:
        print("refused:", exc, flush=True)
        sys.exit(2)
    print("holding", name, flush=True)
    sys.stdin.read()  # hold it until told to go
""")


class Holder:
    """Another process that holds an identity: claimed (``how`` = "claim") or by explicit id."""

    def __init__(self, folder: Path, how: str) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder), how], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, cwd=ROOT)
        self.line = self.proc.stdout.readline().strip()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)


@pytest.fixture
def holders():
    made: list[Holder] = []
    yield lambda folder, how: made.append(Holder(folder, how)) or made[-1]
    for holder in made:
        holder.close()


def serve_args(credentials: Path, actor_id: str = "") -> SimpleNamespace:
    return SimpleNamespace(actor_id=actor_id, bus_credentials=str(credentials), actor_slot=0)


@pytest.mark.slow
def test_an_explicit_actor_id_is_refused_while_another_process_holds_that_identity(tmp_path, holders):
    bus = tmp_path / "bus"
    make_credentials(bus, RUN, actors=2)
    assert holders(bus, "claim").line == "holding actor-0"  # a compose replica holds actor-0
    with pytest.raises(BusCredentialsError, match=r"^actor identity actor-0 is in use by another process"):
        _actor_identity(serve_args(bus, "actor-0"))  # the whole folder, an explicit id
    with pytest.raises(BusCredentialsError, match=r"^actor identity actor-0 is in use by another process"):
        _actor_identity(serve_args(bus / "actor-0"))  # only its own folder
    with pytest.raises(BusCredentialsError, match=r"^actor identity actor-0 is in use by another process"):
        _actor_identity(serve_args(bus / "actor-0", "actor-0"))
    # the control: a free identity named explicitly is taken, and held
    assert _actor_identity(serve_args(bus, "actor-1")) == ("actor-1", None)
    assert str(bus / "actor-1") in identity._HELD


@pytest.mark.slow
def test_serve_actor_with_a_held_explicit_id_stops_with_one_line_and_exit_2(tmp_path, holders):
    bus = tmp_path / "bus"
    make_credentials(bus, RUN, actors=1)
    assert holders(bus, "claim").line == "holding actor-0"
    env = {k: v for k, v in os.environ.items() if not k.startswith("CURLNAV_")}
    result = subprocess.run([*CLI, "serve", "actor", "--run", RUN, "--actor-id", "actor-0", "--bus-credentials",
                             str(bus), "--router", "tcp/127.0.0.1:1", "--router-timeout-s", "1",
                             "--data-dir", str(tmp_path)], capture_output=True, text=True, timeout=180, env=env)
    assert result.returncode == 2, result.stderr[-2000:]
    assert result.stderr.strip().splitlines() == [
        f"curlnav: error: actor identity actor-0 is in use by another process ({bus / 'actor-0'}): each identity "
        f"runs once; give this actor another --actor-id, or none to claim a free one"]


@pytest.mark.slow
def test_a_claiming_replica_never_takes_an_identity_an_explicit_id_holds(tmp_path, holders):
    bus = tmp_path / "bus"
    make_credentials(bus, RUN, actors=2)
    assert holders(bus, "actor-0").line == "holding actor-0"  # `serve actor --actor-id actor-0`
    assert claim_actor_identity(bus).name == "actor-1"


# -- 2 and 3. credentials: only actor-<n>, only real folders and files ----------------------------------

def plant(bus: Path, name: str, password: str = "planted-password") -> None:
    """An identity the credentials tool never minted: ``bus/<name>/user.json``."""
    folder = bus / name
    folder.mkdir(mode=0o700)
    (folder / "user.json").write_text(json.dumps({"role": "actor", "user": name, "password": password, "run": RUN}))
    os.chmod(folder / "user.json", 0o600)


@pytest.mark.parametrize("name", ["actor-$*", "actor-*", "actor-**", "actor-1x", "actor--1", "actor-01",
                                  "actor-\u0663", "actor-1 ", "actor-1.5"])
def test_credentials_refuse_an_identity_not_named_actor_n(tmp_path, name):
    bus = tmp_path / "bus"
    make_credentials(bus, RUN, actors=2)
    acl = (bus / "router" / "acl.json").read_text()
    plant(bus, name)
    with pytest.raises(BusCredentialsError, match="not an actor identity"):
        make_credentials(bus, RUN, actors=2)
    assert (bus / "router" / "acl.json").read_text() == acl  # nothing rewritten
    assert name not in (bus / "router" / "users.txt").read_text()
    assert identity.actor_identities(bus) == ["actor-0", "actor-1"]  # and no replica claims it


@pytest.mark.slow
def test_the_cli_refuses_a_planted_wildcard_identity_with_one_line(tmp_path):
    bus = tmp_path / "bus"
    make_credentials(bus, RUN, actors=2)
    plant(bus, "actor-$*")
    result = subprocess.run([*CLI, "bus", "credentials", "--out", str(bus), "--run", RUN, "--actors", "2"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stdout[-2000:]
    assert result.stderr.strip().splitlines() == [
        f"curlnav: error: {bus / 'actor-$*'} is not an actor identity (actor-<n>, n a number): bus credentials "
        f"never mint it; remove it"]
    assert "actor-$*" not in (bus / "router" / "acl.json").read_text()


def test_a_symlinked_identity_folder_is_refused_and_its_target_left_alone(tmp_path):
    bus, outside = tmp_path / "bus", tmp_path / "outside"
    make_credentials(bus, RUN, actors=1)
    outside.mkdir(mode=0o755)
    os.chmod(outside, 0o755)
    (bus / "actor-1").symlink_to(outside)
    with pytest.raises(BusCredentialsError, match="is a symbolic link"):
        make_credentials(bus, RUN, actors=2)
    assert stat.S_IMODE(outside.stat().st_mode) == 0o755 and list(outside.iterdir()) == []
    assert "actor-1" not in (bus / "router" / "users.txt").read_text()


@pytest.mark.parametrize("where", ["router", "tls", "actor-0/user.json", "router/users.txt", "tls/ca.key"])
def test_credentials_neither_read_nor_write_through_a_symbolic_link(tmp_path, where):
    bus, outside = tmp_path / "bus", tmp_path / "outside"
    tls = {"h0": "10.0.0.1"}
    make_credentials(bus, RUN, actors=1, tls_hosts=tls)
    real = bus / where
    os.rename(real, outside)  # the same content, now outside DIR, reached through a link
    if outside.is_dir():
        os.chmod(outside, 0o755)
    else:
        os.chmod(outside, 0o644)
    real.symlink_to(outside)
    before = {p: (p.read_bytes() if p.is_file() else None, stat.S_IMODE(p.stat().st_mode))
              for p in [outside, *outside.rglob("*")]}
    with pytest.raises(BusCredentialsError, match=f"{real} is a symbolic link"):
        make_credentials(bus, RUN, actors=1, tls_hosts=tls)
    after = {p: (p.read_bytes() if p.is_file() else None, stat.S_IMODE(p.stat().st_mode))
             for p in [outside, *outside.rglob("*")]}
    assert after == before  # nothing written there, nothing chmodded


# -- 2. the planted wildcard at a real router ------------------------------------------------------------

class Inbox:
    def __init__(self) -> None:
        self.items: list[str] = []
        self.lock = threading.Lock()

    def __call__(self, sample) -> None:
        with self.lock:
            self.items.append(f"{sample.key_expr} {sample.payload.to_bytes().decode()}")

    def has(self, item: str) -> bool:
        with self.lock:
            return item in self.items


@pytest.mark.net
@pytest.mark.slow
def test_a_planted_wildcard_identity_puts_nothing_under_other_actors_at_a_real_router(tmp_path):
    """The red team's probe: ``DIR/actor-$*/user.json`` planted, ``curlnav bus credentials`` run
    again, the router started on DIR. The planted user must not get in, and nothing it puts under
    actor-0, actor-2 or actor-999 may reach the replay; actor-0 itself still puts (the control)."""
    bus = tmp_path / "bus"
    make_credentials(bus, RUN, actors=3)
    plant(bus, "actor-$*", "planted-password")
    result = subprocess.run([*CLI, "bus", "credentials", "--out", str(bus), "--run", RUN, "--actors", "3"],
                            capture_output=True, text=True, timeout=120)
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    log = open(tmp_path / "router.log", "wb")
    router = subprocess.Popen([*CLI, "serve", "router", "--run", RUN, "--listen", endpoint, "--bus-credentials",
                               str(bus)], stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    sessions = []
    try:
        def listening() -> bool:
            assert router.poll() is None, (tmp_path / "router.log").read_text()
            try:
                socket.create_connection(("127.0.0.1", port), 0.5).close()
                return True
            except OSError:
                return False

        assert poll(listening, 60, every=0.1), "the router did not listen"
        inbox = Inbox()
        replay = open_session(endpoint, 10.0, user=load_user(bus, "replay", RUN))
        actor = open_session(endpoint, 10.0, user=load_user(bus, "actor", RUN, "actor-0"))
        sessions += [replay, actor]
        replay.declare_subscriber(TOPO.transitions(), inbox)
        try:
            forger = open_session(endpoint, 3.0, user=BusUser("actor", "actor-$*", "planted-password", RUN))
            sessions.append(forger)
        except RouterUnreachable:
            forger = None  # refused at the handshake
        deadline = time.monotonic() + 20
        while not inbox.has(f"{TOPO.transitions('actor-0')} real"):  # the control, and time for the forgeries
            assert time.monotonic() < deadline, "actor-0's own batch never reached the replay"
            actor.put(TOPO.transitions("actor-0"), b"real")
            if forger is not None:
                for victim in ("actor-0", "actor-2", "actor-999"):
                    forger.put(TOPO.transitions(victim), b"forged")
            time.sleep(0.2)
        time.sleep(0.5)
        assert [item for item in inbox.items if "forged" in item] == []
        assert forger is None, "the planted user was let in"
    finally:
        for session in sessions:
            session.close()
        stop([router])
        log.close()
    assert result.returncode == 2 and "actor-$*" not in (bus / "router" / "acl.json").read_text()
    assert "actor-$*" not in (bus / "router" / "users.txt").read_text()


# -- 4. each actor holds only its own identity --------------------------------------------------------

def flag(command: list[str], name: str) -> str:
    return command[command.index(name) + 1]


def files_under(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()}


def passwords(bus: Path) -> dict[str, str]:
    """user -> password of every user minted in ``bus``."""
    return {p.parent.name: json.loads(p.read_text())["password"] for p in bus.glob("*/user.json")}


def started(cluster) -> dict[str, list[str]]:
    """The command line of every service ``cluster.start()`` starts, by name (nothing runs)."""
    out: dict[str, list[str]] = {}
    cluster.spawn = lambda name, cmd: out.setdefault(name, cmd)
    cluster.start()
    return out


@pytest.mark.net
@pytest.mark.slow
def test_local_runs_give_each_actor_only_its_own_identity(tmp_path):
    from curlnav.run.launch import LocalCluster

    cluster = LocalCluster(tmp_path / "run", actors=2, run=RUN)
    secret = passwords(cluster.bus_dir)
    commands = started(cluster)
    for n in range(2):
        folder = Path(flag(commands[f"actor-{n}"], "--bus-credentials"))
        assert files_under(folder) == {"user.json"}, f"actor-{n} holds {sorted(files_under(folder))}"
        assert load_user(folder, "actor", RUN, f"actor-{n}").password == secret[f"actor-{n}"]
    for name, cmd in commands.items():  # no service but the router holds another user's password
        folder = Path(flag(cmd, "--bus-credentials"))
        own = name.split("-")[0] if name.split("-")[0] != "actor" else name
        held = "".join(p.read_text() for p in folder.rglob("*") if p.is_file())
        if name != "router":
            assert [user for user, password in secret.items() if password in held and user != own] == [], name
        assert "ca.key" not in files_under(folder)


def test_the_hosts_bench_gives_each_actor_only_its_identity_and_no_actor_host_the_ca_key(tmp_path):
    from curlnav.bench.hosts import HostsCluster

    cluster = HostsCluster(tmp_path / "run", Namespaces(), actors_per_host=2, run=RUN)
    secret = passwords(cluster.bus_dir)
    commands = started(cluster)
    held_by_host: dict[int, set[str]] = {}
    for name, cmd in commands.items():
        host = int(cmd[3].removeprefix("host"))
        folder = Path(flag(cmd, "--bus-credentials"))
        held_by_host.setdefault(host, set()).update(str(p.resolve()) for p in folder.rglob("*") if p.is_file())
        if name.startswith("actor-"):
            assert files_under(folder) == {"user.json"}, f"{name} holds {sorted(files_under(folder))}"
            assert load_user(folder, "actor", RUN, name).password == secret[name]
        if name.startswith("router-"):  # what a router needs: its users, access control, CA certificate, own pair
            router_name = name.removeprefix("router-")
            assert files_under(folder) == {"user.json", "users.txt", "acl.json", "tls/ca.pem",
                                           f"tls/{router_name}.pem", f"tls/{router_name}.key"}, name
            load_router(folder)
            load_tls(folder, router_name)
            host = int(router_name.removeprefix("h"))
            services = {"replay", "learner", "scheduler"} if host == 0 else \
                {f"actor-{n}" for n in range(4) if cluster.host_of(f"actor-{n}") == host}
            dictionary = dict(line.split(":", 1) for line in (folder / "users.txt").read_text().splitlines())
            # the users this router authenticates: its host's services, and the other routers' links
            assert set(dictionary) == services | {"router"}, f"{name}: {sorted(dictionary)}"
            assert all(secret[user] == password for user, password in dictionary.items()), name
    for host, held in held_by_host.items():
        names = {Path(p).name for p in held}
        assert "ca.key" not in names, f"host {host} holds the CA key"
        assert {f"h{i}.key" for i in range(3)} & names == {f"h{host}.key"}, f"host {host}: {sorted(names)}"
        own = {"replay", "learner", "scheduler"} if host == 0 else \
            {f"actor-{n}" for n in range(4) if cluster.host_of(f"actor-{n}") == host}
        users = {Path(p).parent.name for p in held if Path(p).name == "user.json"} - {"router"}
        assert users == own, host
        # no file of the host, its router's dictionary included, holds another host's service's password
        others = {user: password for user, password in secret.items() if user not in own | {"router"}}
        texts = "".join(Path(p).read_text() for p in held)
        assert [user for user, password in others.items() if password in texts] == [], f"host {host}"


BUS_CLIENT = textwrap.dedent('''
    import os, sys, time
    from curlnav.bus.security import load_user
    from curlnav.bus.transport import open_session
    role, folder, run, seconds = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
    user = load_user(folder, "actor" if role.startswith("actor-") else role, run,
                     role if role.startswith("actor-") else None)
    s = open_session("tcp/127.0.0.1:7448", 20, user=user)
    got = []
    if role == "replay":
        s.declare_subscriber(f"curlnav/{run}/transitions/*", lambda x: got.append(str(x.key_expr)))
    end = time.time() + seconds
    while time.time() < end:
        if role != "replay":
            s.put(f"curlnav/{run}/transitions/{role}", b"batch")
        time.sleep(0.2)
    print("received", sorted(set(got)), len(got), flush=True)
    os._exit(0)  # a zenoh session may hang at interpreter exit
''')


@pytest.mark.slow
@pytest.mark.skipif(unavailable() is not None, reason=f"no network namespaces here: {unavailable()}")
def test_the_hosts_bench_credentials_link_two_hosts_without_the_ca_key(tmp_path):
    """A short real run of what the bench gives each host: two namespaces, each router with only
    its own folder (no CA key), an actor on host 1 with only its ``user.json``; its batches reach
    the replay on host 0 through the routers' mutual-TLS link."""
    from curlnav.bench.hosts import HostsCluster

    with Hosts(2, tag=f"i{os.getpid() % 10000}") as net:
        cluster = HostsCluster(tmp_path / "run", net, actors_per_host=1, run=RUN)
        commands = started(cluster)  # the bench's command lines; only the routers run here
        procs: list[subprocess.Popen] = []
        try:
            for i in range(2):
                assert not any(p.name == "ca.key" for p in (tmp_path / "run" / f"h{i}").rglob("*"))
                procs.append(subprocess.Popen(commands[f"router-h{i}"], stdout=subprocess.DEVNULL,
                                              stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL))
            actor = Path(flag(commands["actor-0"], "--bus-credentials"))
            assert files_under(actor) == {"user.json"}
            script = tmp_path / "client.py"
            script.write_text(BUS_CLIENT)
            replay_folder = tmp_path / "run" / "h0" / "bus" / "replay"
            replay = subprocess.Popen([*net.exec(0), sys.executable, str(script), "replay", str(replay_folder), RUN,
                                       "25"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            procs.append(replay)
            procs.append(subprocess.Popen([*net.exec(1), sys.executable, str(script), "actor-0", str(actor), RUN, "25"],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT))
            out, _ = replay.communicate(timeout=90)
            assert f"received ['curlnav/{RUN}/transitions/actor-0']" in out, out[-2000:]
        finally:
            stop(procs)
