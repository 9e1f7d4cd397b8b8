"""The authenticated bus: a real router process (`curlnav serve router --bus-credentials DIR`)
refuses sessions without the run's credentials and lets each role send only what its row of the
access-control table allows. Every forgery is checked against a subscriber (or querier) that is
allowed to receive, and every refusal has a control that the same path works for the right
role, so these tests can fail. Every wait polls with a deadline; every process is stopped."""

from __future__ import annotations

import functools
import json
import os
import socket
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import zenoh
from conftest import wait_for

from curlnav.bus import identity
from curlnav.bus.security import (
    ALLOWED,
    ROLES,
    BusCredentialsError,
    BusUser,
    access_control,
    actor_ids,
    allowed,
    load_router,
    load_user,
    make_credentials,
    permissions,
)
from curlnav.bus.transport import RouterUnreachable, open_session
from curlnav.proto.messages import EpisodeReport, Weights
from curlnav.proto.topology import Topology
from curlnav.run.launch import free_port

RUN = "authtest"
TOPO = Topology(RUN)
REFUSAL_TIMEOUT_S = 3.0  # how long a refused session tries before it gives up


wait_for = functools.partial(wait_for, timeout=20.0, every=0.05)  # the bus answers within ms: poll often


# -- the credentials and the table, without a router ------------------------------------------------

def test_credentials_are_private_kept_and_bound_to_their_run(tmp_path):
    bus = tmp_path / "bus"
    users_made = [*ROLES, *actor_ids(8)]  # the services, and one user per actor (8 by default)
    assert make_credentials(bus, RUN) == {name: "created" for name in users_made}
    assert stat.S_IMODE(bus.stat().st_mode) == 0o700
    for path in bus.rglob("*"):
        assert stat.S_IMODE(path.stat().st_mode) == (0o700 if path.is_dir() else 0o600), path
    users = {role: load_user(bus, role, RUN) for role in ROLES}
    assert len({u.password for u in users.values()}) == len(ROLES)  # one random password per role
    actors = {a: load_user(bus, "actor", RUN, a) for a in actor_ids(8)}
    assert [a.user for a in actors.values()] == actor_ids(8) and len({a.password for a in actors.values()}) == 8
    lines = (bus / "router" / "users.txt").read_text().splitlines()
    assert sorted(lines) == sorted(f"{u.user}:{u.password}" for u in [*users.values(), *actors.values()])
    with pytest.raises(BusCredentialsError, match="belong to actor 'actor-1', this actor is 'actor-0'"):
        load_user(bus / "actor-1", "actor", RUN, "actor-0")  # an actor given another's folder
    # a second call (--resume, a compose restart) keeps every password
    assert make_credentials(bus, RUN) == {name: "kept" for name in users_made}
    assert {role: load_user(bus, role).password for role in ROLES} == {r: u.password for r, u in users.items()}
    # another run: the same users, the access control rewritten for its prefix
    make_credentials(bus, "other")
    assert load_user(bus, "actor", "other", "actor-0").password == actors["actor-0"].password
    assert "curlnav/other/weights" in json.dumps(load_router(bus).access_control)
    with pytest.raises(BusCredentialsError, match="for run 'other'"):
        load_user(bus, "actor", RUN, "actor-0")
    # a role's own folder (what a container mounts), and no other role's
    assert load_user(bus / "learner", "learner").password == users["learner"].password
    with pytest.raises(BusCredentialsError, match="the learner's, not the actor's"):
        load_user(bus / "learner", "actor")
    with pytest.raises(BusCredentialsError, match="no bus credentials"):
        load_user(tmp_path / "nowhere", "actor")
    assert load_router(bus / "router").users_file == (bus / "router" / "users.txt").resolve()


def test_the_table_names_only_topology_keys_and_the_acl_is_default_deny():
    topo = Topology("x")
    known = {topo.transitions(), topo.episodes(), topo.assign, topo.sample, topo.credit, topo.weights,
             topo.weights_latest, topo.status(), topo.status("replay"), topo.status("learner"), topo.priorities,
             topo.alive("actor")}
    for role, rows in ALLOWED.items():
        for _message, key in rows:
            assert f"{topo.prefix}/{key.format(id='*')}" in known, (role, key)
    acl = access_control("x", actor_ids(2))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert {p["id"] for p in acl["policies"]} == {*ROLES, "actor-0", "actor-1"}
    perms = permissions("x", actor_ids(2))
    user_of = {"actor": "actor-0"}

    def who(message: str, key: str, flow: str = "ingress") -> list[str]:
        """The roles allowed ``message`` on ``key`` (Zenoh: an allowed key expression includes it)."""
        return [role for role in ALLOWED if any(zenoh.KeyExpr(k).includes(zenoh.KeyExpr(key))
                                                for k in perms[user_of.get(role, role)].get((flow, message), ()))]

    assert who("put", topo.weights) == ["learner"] and who("put", topo.priorities) == ["learner"]
    assert who("put", topo.credit) == ["replay"] and who("put", topo.status("replay")) == ["replay"]
    assert who("put", topo.episodes("actor-0")) == ["actor"] and who("put", topo.transitions("actor-0")) == ["actor"]
    assert who("put", topo.episodes("actor-1")) == [] and who("put", topo.transitions("actor-1")) == []  # not its id
    assert who("put", topo.status("evil")) == [] and who("put", topo.alive("actor", "a")) == []
    assert who("declare_queryable", topo.sample) == ["replay"] and who("query", topo.sample) == ["learner"]
    assert who("declare_queryable", topo.weights_latest) == ["learner"]
    assert who("declare_queryable", topo.assign) == ["scheduler"] and who("query", topo.assign) == ["actor"]
    assert who("declare_subscriber", topo.transitions()) == ["replay"]
    assert who("declare_subscriber", topo.weights) == ["actor"]
    assert who("put", topo.weights, "egress") == ["actor"] and who("reply", topo.sample, "egress") == ["learner"]
    assert who("declare_queryable", topo.config("replay", "r")) == ["replay"]
    assert who("declare_queryable", topo.config("actor", "a")) == []  # actors never answer for the run's config
    assert who("query", topo.config()) == list(ALLOWED)  # the config agreement: everyone asks
    assert all(who(m, topo.prefix + "/**") == [] for m in ("put", "delete", "declare_subscriber", "query"))
    for role in ALLOWED:  # liveliness tokens only under alive/<role>/ (an actor: its own id)
        assert perms[user_of.get(role, role)]["ingress", "liveliness_token"] == [
            topo.alive(role, "actor-0" if role == "actor" else "*")]
    assert [r for r in ALLOWED if ("ingress", "declare_liveliness_subscriber") in perms[user_of.get(r, r)]] == [
        "replay", "scheduler"]


@pytest.mark.slow
def test_cli_writes_credentials(tmp_path):
    out = tmp_path / "bus"
    result = subprocess.run([sys.executable, "-m", "curlnav.cli", "bus", "credentials", "--out", str(out),
                             "--run", RUN], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "actor-0 (created)" in result.stdout and "default deny" in result.stdout
    assert load_user(out, "scheduler", RUN).user == "scheduler"


# -- a real router ------------------------------------------------------------------------------------

class Bus:
    """A router process with the run's credentials, and sessions to it."""

    def __init__(self, folder: Path) -> None:
        self.credentials = folder / "bus"
        make_credentials(self.credentials, RUN)
        port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{port}"
        self.log = open(folder / "router.log", "wb")
        self.proc = subprocess.Popen([sys.executable, "-m", "curlnav.cli", "serve", "router", "--run", RUN,
                                      "--listen", self.endpoint, "--bus-credentials", str(self.credentials)],
                                     stdout=self.log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        self.sessions: list[zenoh.Session] = []

        def listening() -> bool:
            assert self.proc.poll() is None, (folder / "router.log").read_text()
            try:
                socket.create_connection(("127.0.0.1", port), 0.5).close()
                return True
            except OSError:
                return False

        wait_for("the router to listen", listening, timeout=60)

    def user(self, role: str, ident: str = "actor-0") -> BusUser:
        return load_user(self.credentials, role, RUN, ident if role == "actor" else None)

    def session(self, role: str, ident: str = "actor-0") -> zenoh.Session:
        """A session authenticated as ``role`` (an actor: as actor ``ident``)."""
        session = open_session(self.endpoint, 10.0, user=self.user(role, ident))
        self.sessions.append(session)
        return session

    def refused(self, user: BusUser | None) -> bool:
        """Whether a session as ``user`` (None: no credentials) is refused."""
        try:
            self.sessions.append(open_session(self.endpoint, REFUSAL_TIMEOUT_S, user=user))
        except RouterUnreachable:
            return True
        return False

    def close(self) -> None:
        for session in self.sessions:
            session.close()
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.log.close()


@pytest.fixture(scope="module")
def bus(tmp_path_factory):
    b = Bus(tmp_path_factory.mktemp("bus"))
    try:
        yield b
    finally:
        b.close()


class Inbox:
    """What a subscriber received, thread-safe."""

    def __init__(self) -> None:
        self.items: list[bytes] = []
        self.lock = threading.Lock()

    def __call__(self, sample) -> None:
        self.add(sample.payload.to_bytes())

    def add(self, item: bytes) -> None:
        with self.lock:
            self.items.append(item)

    def has(self, payload: bytes) -> bool:
        with self.lock:
            return payload in self.items


def weights(version: int) -> bytes:
    return Weights(version, version, b"\x00" * 16, {"forged": version}).encode()


def deliver_until(publisher_put, payload: bytes, inbox: Inbox, what: str) -> None:
    """Put ``payload`` every 0.2 s until ``inbox`` has it (declarations take a moment to spread)."""
    deadline = time.monotonic() + 20
    while not inbox.has(payload):
        assert time.monotonic() < deadline, f"timed out: {what}"
        publisher_put(payload)
        time.sleep(0.2)


@pytest.mark.net
@pytest.mark.slow
def test_a_session_without_credentials_is_refused_and_its_weights_never_arrive(bus):
    inbox = Inbox()
    bus.session("actor").declare_subscriber(TOPO.weights, inbox)
    learner = bus.session("learner")
    deliver_until(lambda p: learner.put(TOPO.weights, p), weights(1), inbox, "the learner's weights reach the actor")
    try:  # a raw Zenoh client, no credentials at all
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([bus.endpoint]))
        conf.insert_json5("connect/timeout_ms", str(int(REFUSAL_TIMEOUT_S * 1000)))
        forger = zenoh.open(conf)
    except zenoh.ZError:
        forger = None
    if forger is not None:  # it must not be let in; if it were, it must not be believed
        bus.sessions.append(forger)
        for version in range(100, 110):
            forger.put(TOPO.weights, weights(version))
    assert bus.refused(None)
    deliver_until(lambda p: learner.put(TOPO.weights, p), weights(2), inbox, "a later legitimate put")
    time.sleep(0.5)
    assert forger is None
    assert not any(inbox.has(weights(v)) for v in range(100, 110))


@pytest.mark.net
@pytest.mark.slow
def test_a_wrong_password_or_another_runs_credentials_are_refused(bus, tmp_path):
    actor = bus.user("actor")
    assert bus.refused(BusUser("actor", "actor", actor.password + "x", RUN))
    assert bus.refused(BusUser("actor", "nobody", actor.password, RUN))
    make_credentials(tmp_path / "other", RUN)  # another set: same users, other passwords
    assert bus.refused(load_user(tmp_path / "other", "learner"))
    assert not bus.refused(actor)  # the control: the right password gets in


@pytest.mark.net
@pytest.mark.slow
def test_actor_credentials_cannot_forge_weights_status_priorities_or_credit(bus):
    actor, learner, replay = bus.session("actor"), bus.session("learner"), bus.session("replay")
    listeners = {"weights": (bus.session("actor"), TOPO.weights), "status": (bus.session("scheduler"), TOPO.status()),
                 "priorities": (replay, TOPO.priorities), "credit": (bus.session("actor"), TOPO.credit)}
    inboxes = {}
    for name, (session, key) in listeners.items():
        inboxes[name] = Inbox()
        session.declare_subscriber(key, inboxes[name])
    legit = {"weights": (learner, TOPO.weights), "status": (learner, TOPO.status("learner")),
             "priorities": (learner, TOPO.priorities), "credit": (replay, TOPO.credit)}
    forged = {"weights": TOPO.weights, "status": TOPO.status("learner"), "priorities": TOPO.priorities,
              "credit": TOPO.credit}
    for name, key in forged.items():
        session, legit_key = legit[name]
        deliver_until(lambda p: session.put(legit_key, p), f"{name} legit 1".encode(), inboxes[name],
                      f"the {name} of the right role")
        for i in range(20):
            actor.put(key, f"{name} forged {i}".encode())
        deliver_until(lambda p: session.put(legit_key, p), f"{name} legit 2".encode(), inboxes[name],
                      f"the {name} of the right role, after the forgeries")
    time.sleep(0.5)
    assert {name: [p for p in inbox.items if b"forged" in p] for name, inbox in inboxes.items()} == \
        {name: [] for name in forged}  # 80 forged puts, none believed


@pytest.mark.net
@pytest.mark.slow
def test_learner_credentials_cannot_forge_episodes_or_transitions(bus):
    scheduler, replay = bus.session("scheduler"), bus.session("replay")
    episodes, transitions = Inbox(), Inbox()
    scheduler.declare_subscriber(TOPO.episodes(), episodes)
    replay.declare_subscriber(TOPO.transitions(), transitions)
    report = EpisodeReport("actor-0", "open-room", "across", True, 1.0, 0, 0, 10, 1, 0).encode()
    learner, actor = bus.session("learner"), bus.session("actor")
    for _i in range(20):
        learner.put(TOPO.episodes("actor-0"), report + b"forged")
        learner.put(TOPO.transitions("actor-0"), b"forged")
    deliver_until(lambda p: actor.put(TOPO.episodes("actor-0"), p), report, episodes, "an actor's report")
    deliver_until(lambda p: actor.put(TOPO.transitions("actor-0"), p), b"batch", transitions, "an actor's batch")
    time.sleep(0.5)
    assert not episodes.has(report + b"forged") and not transitions.has(b"forged")


@pytest.mark.net
@pytest.mark.slow
def test_an_actor_cannot_write_under_another_actors_id(bus):
    """One identity per actor (issue 30): actor-1's own credentials put nothing under actor-0's id
    (transitions, episode reports); the control: actor-0 puts under its own."""
    scheduler, replay = bus.session("scheduler"), bus.session("replay")
    episodes, transitions = Inbox(), Inbox()
    scheduler.declare_subscriber(TOPO.episodes(), lambda s: episodes.add(str(s.key_expr).encode() + b" "
                                                                         + s.payload.to_bytes()))
    replay.declare_subscriber(TOPO.transitions(), lambda s: transitions.add(str(s.key_expr).encode() + b" "
                                                                            + s.payload.to_bytes()))
    forger, actor = bus.session("actor", "actor-1"), bus.session("actor", "actor-0")
    for _ in range(20):
        forger.put(TOPO.episodes("actor-0"), b"forged report")
        forger.put(TOPO.transitions("actor-0"), b"forged batch")
    key = TOPO.transitions("actor-0").encode()
    deliver_until(lambda p: actor.put(TOPO.transitions("actor-0"), p.split(b" ", 1)[1]), key + b" real batch",
                  transitions, "actor-0's own batch")
    deliver_until(lambda p: forger.put(TOPO.transitions("actor-1"), p.split(b" ", 1)[1]),
                  TOPO.transitions("actor-1").encode() + b" its own", transitions, "actor-1's batch under its own id")
    time.sleep(0.5)
    assert not any(b"forged" in item for item in transitions.items + episodes.items)


@pytest.mark.net
@pytest.mark.slow
def test_compose_replicas_claim_their_own_identity_and_cannot_write_under_each_others_id(bus):
    """Compose replicas (issue 30): each claims an identity from the folder of every actor's
    credentials (the ``bus-actors`` volume; ``curlnav serve actor`` without --actor-id) and
    authenticates as it, as ``ServiceShell`` does; the second replica puts nothing under the
    first's id, and each puts under its own."""
    from curlnav.run.launch import _actor_identity

    def replica() -> tuple[str, zenoh.Session]:
        ident, _ = _actor_identity(SimpleNamespace(actor_id="", actor_slot=0, bus_credentials=str(bus.credentials)))
        session = open_session(bus.endpoint, 10.0, user=load_user(bus.credentials, "actor", RUN, ident))
        bus.sessions.append(session)
        return ident, session

    claims = dict(identity._HELD)
    try:
        (first, a), (second, b) = replica(), replica()
    finally:
        for key in set(identity._HELD) - set(claims):
            identity._HELD[key].release()
    assert first != second and {first, second} <= set(actor_ids(8))
    transitions, episodes = Inbox(), Inbox()
    bus.session("replay").declare_subscriber(TOPO.transitions(), lambda s: transitions.add(
        str(s.key_expr).encode() + b" " + s.payload.to_bytes()))
    bus.session("scheduler").declare_subscriber(TOPO.episodes(), episodes)
    for _ in range(20):
        b.put(TOPO.transitions(first), b"forged batch")
        b.put(TOPO.episodes(first), b"forged report")
    for ident, session in ((first, a), (second, b)):
        key = TOPO.transitions(ident).encode()
        deliver_until(lambda p, s=session, i=ident: s.put(TOPO.transitions(i), p.split(b" ", 1)[1]),
                      key + b" own batch", transitions, f"{ident}'s batch under its own id")
    time.sleep(0.5)
    assert not any(b"forged" in item for item in transitions.items + episodes.items)


@pytest.mark.net
@pytest.mark.slow
def test_only_the_replay_answers_samples_and_only_the_learner_asks(bus):
    learner = bus.session("learner")

    def answers(session) -> list[bytes]:
        return [r.ok.payload.to_bytes() for r in session.get(TOPO.sample, payload=b"req", timeout=2.0)
                if r.ok is not None]

    bus.session("actor").declare_queryable(TOPO.sample, lambda q: q.reply(TOPO.sample, b"forged sample"))
    bus.session("scheduler").declare_queryable(TOPO.sample, lambda q: q.reply(TOPO.sample, b"forged sample"))
    time.sleep(0.5)
    assert answers(learner) == []  # forged queryables are never declared at the router
    bus.session("replay").declare_queryable(TOPO.sample, lambda q: q.reply(TOPO.sample, b"real sample"))
    wait_for("the replay's answer", lambda: answers(learner) == [b"real sample"])
    assert answers(bus.session("actor")) == []  # an actor may not read the replay
    # nor may it answer the actors' own assignment or weights queries in the scheduler's or learner's place
    actor = bus.session("actor")
    actor.declare_queryable(TOPO.assign, lambda q: q.reply(TOPO.assign, b"forged assignment"))
    actor.declare_queryable(TOPO.weights_latest, lambda q: q.reply(TOPO.weights_latest, b"forged weights"))
    time.sleep(0.5)
    other = bus.session("actor")
    assert [r.ok for r in other.get(TOPO.assign, timeout=1.5) if r.ok is not None] == []
    assert [r.ok for r in other.get(TOPO.weights_latest, timeout=1.5) if r.ok is not None] == []


@pytest.mark.net
@pytest.mark.slow
def test_fake_liveliness_tokens_are_not_seen_by_the_scheduler(bus):
    def watch(role: str, key: str) -> Inbox:
        seen = Inbox()
        bus.session(role).liveliness().declare_subscriber(key, lambda s: seen.add(str(s.key_expr).encode()),
                                                          history=True)
        return seen

    seen = watch("scheduler", TOPO.alive("actor"))
    assert bus.refused(None)  # an unauthenticated session cannot declare anything
    for role in ("learner", "replay", "scheduler"):  # phantom actors from the other roles
        bus.session(role).liveliness().declare_token(TOPO.alive("actor", f"phantom-{role}"))
    bus.session("actor", "actor-1").liveliness().declare_token(TOPO.alive("actor", "phantom-actor-1"))  # not its id
    bus.session("actor").liveliness().declare_token(TOPO.alive("actor", "actor-0"))
    wait_for("the real actor's token", lambda: seen.has(TOPO.alive("actor", "actor-0").encode()))
    time.sleep(0.5)
    assert [k for k in seen.items if b"phantom" in k] == []
    # an actor's token outside alive/actor/ is refused too (the router's own user may watch everything)
    everything = watch("router", f"{TOPO.prefix}/alive/**")
    bus.session("actor").liveliness().declare_token(TOPO.alive("learner", "phantom"))
    bus.session("learner").liveliness().declare_token(TOPO.alive("learner", "real"))
    wait_for("the real learner's token", lambda: everything.has(TOPO.alive("learner", "real").encode()))
    time.sleep(0.5)
    assert [k for k in everything.items if b"phantom" in k] == []
    # and the scheduler may watch alive/actor/* only
    watcher = watch("scheduler", TOPO.alive("learner"))
    time.sleep(1.0)
    assert watcher.items == []


@pytest.mark.slow
def test_a_service_with_another_runs_credentials_stops_with_one_line(tmp_path):
    make_credentials(tmp_path / "bus", "other")
    env = {k: v for k, v in os.environ.items() if not k.startswith("CURLNAV_")}
    result = subprocess.run([sys.executable, "-m", "curlnav.cli", "serve", "replay", "--run", RUN,
                             "--router", "tcp/127.0.0.1:1", "--router-timeout-s", "1", "--data-dir", str(tmp_path),
                             "--bus-credentials", str(tmp_path / "bus")],
                            capture_output=True, text=True, timeout=180, env=env)
    assert result.returncode == 2
    assert "curlnav: error: the bus credentials" in result.stderr and "for run 'other'" in result.stderr


def test_the_readme_table_is_the_code_table():
    """The docs' "Bus security" table shows ``allowed(role)`` for every role, nothing more or less."""
    readme = (Path(__file__).resolve().parent.parent / "docs" / "guide" / "bus-security.md").read_text()
    columns = {1: "put", 2: "declare_subscriber", 3: "query", 4: "declare_queryable"}
    for role in ALLOWED:
        row = next(line for line in readme.splitlines() if line.startswith(f"| {role} |"))
        cells = [c.strip() for c in row.strip("|").split("|")][1:]
        shown = {(columns[i + 1], k.strip().strip("`")) for i, cell in enumerate(cells[:4])
                 for k in cell.split(",") if k.strip()}
        live = cells[4]
        shown.add(("liveliness_token", live.split("token ")[1].split("`")[1]))
        if "watches" in live:
            shown.add(("declare_liveliness_subscriber", live.split("watches ")[1].strip("`")))
        assert shown == set(allowed(role, "<own id>")), role
