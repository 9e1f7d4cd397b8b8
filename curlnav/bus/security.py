"""A run's bus credentials and access control: nothing forged is believed.

Without them, anyone who reaches the Zenoh router could publish weights (actors run them),
episode reports (they advance the curriculum) or liveliness tokens (phantom actors), and query
the replay. With them, Zenoh's own mechanisms guard the bus:

* **user-password authentication** (``transport/auth/usrpwd``): the router admits only the
  run's users, one per role, listed ``user:password`` in its dictionary file; a session with no
  password or a wrong one is refused at the handshake (challenge-response: the password never
  crosses the wire; the traffic itself is not encrypted);
* **access control** (``access_control``): default deny; each role may send and declare only what
  ``ALLOWED`` lists, under its run's prefix ``curlnav/<run>/``, and receive only what follows from
  it (``permissions``).

Layout (``curlnav bus credentials --out DIR``; folders 0700, files 0600)::

    DIR/router/users.txt   the router's dictionary: ``user:password``, one line per role
    DIR/router/acl.json    the router's ``access_control`` block, made from ``ALLOWED``
    DIR/router/user.json   the router's own user (links to other routers, ``--connect``)
    DIR/<role>/user.json   {"role", "user", "password", "run"}: replay, learner, scheduler, actor

A service is given DIR (it reads ``DIR/<role>/``) or only its own folder: containers mount only
their own, so an actor never holds the learner's password. The evaluator uses HTTP only.
"""

from __future__ import annotations

import json
import os
import secrets
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from curlnav.proto.topology import Topology

PUT, SUBSCRIBE, QUERY, QUERYABLE = "put", "declare_subscriber", "query", "declare_queryable"
REPLY, TOKEN, WATCH = "reply", "liveliness_token", "declare_liveliness_subscriber"
MESSAGES = (PUT, "delete", SUBSCRIBE, QUERY, QUERYABLE, REPLY, TOKEN, WATCH, "liveliness_query")

#: What each role may send or declare, as (message, key under ``curlnav/<run>/``); every key is one
#: of ``proto/topology.py``. Nobody may delete; the scheduler and the replay watch the actors'
#: liveliness (the live actors, their acknowledgements), nobody watches the services'.
ALLOWED: dict[str, tuple[tuple[str, str], ...]] = {
    "replay": ((SUBSCRIBE, "transitions/*"), (SUBSCRIBE, "replay/priorities"), (QUERYABLE, "replay/sample"),
               (PUT, "replay/credit"), (PUT, "status/replay"), (WATCH, "alive/actor/*")),
    "learner": ((PUT, "weights"), (QUERYABLE, "weights/latest"), (QUERY, "replay/sample"),
                (PUT, "replay/priorities"), (PUT, "status/learner"), (SUBSCRIBE, "status/replay")),
    "scheduler": ((QUERYABLE, "scheduler/assign"), (SUBSCRIBE, "episodes/*"), (SUBSCRIBE, "status/*"),
                  (WATCH, "alive/actor/*")),
    "actor": ((PUT, "transitions/*"), (PUT, "episodes/*"), (QUERY, "scheduler/assign"), (SUBSCRIBE, "weights"),
              (QUERY, "weights/latest"), (SUBSCRIBE, "replay/credit")),
}
SERVICE_ROLES = tuple(ALLOWED)
ROLES = ("router", *SERVICE_ROLES)  # one bus user each
#: the roles whose answers make the run's config (``ServiceShell``'s agreement): an actor joins
#: a run on their config and never answers for it, so no actor can veto another service
CONFIG_OWNERS = ("replay", "learner", "scheduler")


class BusCredentialsError(ValueError):
    """Missing, unreadable or mismatched bus credentials."""


@dataclass(frozen=True)
class BusUser:
    role: str
    user: str
    password: str
    run: str


@dataclass(frozen=True)
class RouterAuth:
    """What the router loads: its dictionary file, its access control and its own user."""

    users_file: Path
    access_control: dict
    user: BusUser


def allowed(role: str) -> tuple[tuple[str, str], ...]:
    """``ALLOWED[role]`` plus what every service does (``ServiceShell``): ask ``config/*/*`` (the
    config agreement), hold ``alive/<role>/<id>``, and, for ``CONFIG_OWNERS``, answer
    ``config/<role>/<id>``."""
    answer = ((QUERYABLE, f"config/{role}/*"),) if role in CONFIG_OWNERS else ()
    return ALLOWED[role] + answer + ((QUERY, "config/*/*"), (TOKEN, f"alive/{role}/*"))


def permissions(run: str) -> dict[str, dict[tuple[str, str], list[str]]]:
    """role -> (flow, message) -> full key expressions it is allowed on. Ingress (into the router)
    is ``allowed(role)`` itself; egress (to the role) follows from it: a subscriber receives puts
    on its key, a querier replies, a queryable the queries that meet its key; a publisher learns
    the subscribers that meet its key (Zenoh sends a put only when it knows of one) and a querier
    the queryables. Zenoh grants a message when an allowed key expression *includes* its key."""
    import zenoh

    prefix = Topology(run).prefix
    rows = {role: [(message, f"{prefix}/{key}") for message, key in allowed(role)] for role in ALLOWED}
    every = [row for role_rows in rows.values() for row in role_rows]

    def meeting(message: str, key: str) -> set[str]:
        return {k for m, k in every if m == message and zenoh.KeyExpr(k).intersects(zenoh.KeyExpr(key))}

    out = {}
    for role, role_rows in rows.items():
        perms: dict[tuple[str, str], set[str]] = defaultdict(set)
        for message, key in role_rows:
            perms["ingress", message].add(key)
            if message == PUT:
                perms["egress", SUBSCRIBE] |= meeting(SUBSCRIBE, key)
            elif message == SUBSCRIBE:
                perms["egress", PUT].add(key)
            elif message == QUERY:
                perms["egress", REPLY].add(key)
                perms["egress", QUERYABLE] |= meeting(QUERYABLE, key)
            elif message == QUERYABLE:
                perms["ingress", REPLY].add(key)
                perms["egress", QUERY] |= meeting(QUERY, key)
            elif message == WATCH:
                perms["egress", TOKEN].add(key)
        out[role] = {flow_message: sorted(keys) for flow_message, keys in sorted(perms.items()) if keys}
    return out


def access_control(run: str) -> dict:
    """The router's ``access_control`` block: default deny, one rule per (role, flow, message),
    one subject (its username) and one policy per role; routers joined with ``--connect``
    (the ``router`` user) relay everything of the run."""
    rules, subjects, policies = [], [], []
    for role, perms in permissions(run).items():
        ids = []
        for (flow, message), keys in perms.items():
            ids.append(f"{role} {flow} {message}")
            rules.append({"id": ids[-1], "permission": "allow", "flows": [flow], "messages": [message],
                          "key_exprs": keys})
        subjects.append({"id": role, "usernames": [role]})
        policies.append({"id": role, "rules": ids, "subjects": [role]})
    rules.append({"id": "router links", "permission": "allow", "flows": ["ingress", "egress"],
                  "messages": list(MESSAGES), "key_exprs": [f"{Topology(run).prefix}/**"]})
    subjects.append({"id": "router", "usernames": ["router"]})
    policies.append({"id": "router", "rules": ["router links"], "subjects": ["router"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` (mode 0600, atomically), unless it already holds it."""
    try:
        if path.read_text() == text:
            os.chmod(path, 0o600)
            return
    except OSError:
        pass
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        os.fchmod(f.fileno(), 0o600)
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _private_dir(path: Path) -> Path:
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(path, 0o700)
    return path


def _read_user(path: Path) -> BusUser:
    try:
        d = json.loads(path.read_text())
        return BusUser(str(d["role"]), str(d["user"]), str(d["password"]), str(d["run"]))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise BusCredentialsError(f"unreadable bus credentials {path}: {exc}") from None


def make_credentials(out: str | Path, run: str) -> dict[str, str]:
    """Write (or complete) the bus credentials of ``run`` into ``out``: one user per role with a
    random password, the router's dictionary and access control. Passwords already there are
    kept (``--resume``, a compose restart); the access control is rewritten for ``run``.
    Returns role -> "created" or "kept"."""
    Topology(run)  # a bad run name fails here
    out = _private_dir(Path(out))
    users, done = {}, {}
    for role in ROLES:
        path = _private_dir(out / role) / "user.json"
        try:
            user = _read_user(path)
            done[role] = "kept"
        except BusCredentialsError:
            user, done[role] = BusUser(role, role, secrets.token_urlsafe(24), run), "created"
        if user.role != role or user.user != role:
            raise BusCredentialsError(f"{path} holds the {user.role}'s credentials, not the {role}'s")
        users[role] = BusUser(role, role, user.password, run)
        _write_private(path, json.dumps(users[role].__dict__, indent=1) + "\n")
    _write_private(out / "router" / "users.txt", "".join(f"{u.user}:{u.password}\n" for u in users.values()))
    _write_private(out / "router" / "acl.json", json.dumps(access_control(run), indent=1) + "\n")
    return done


def _role_folder(path: str | Path, role: str) -> Path:
    """``path/<role>`` (a run's credentials folder) or ``path`` itself (one role's folder)."""
    path = Path(path)
    if (path / role / "user.json").is_file():
        return path / role
    if (path / "user.json").is_file():
        return path
    raise BusCredentialsError(f"no bus credentials for the {role} in {path} "
                              f"(make them with `curlnav bus credentials --out DIR`)")


def load_user(path: str | Path, role: str, run: str | None = None) -> BusUser:
    """The bus user of ``role`` from ``path``; refused if they belong to another role or run."""
    folder = _role_folder(path, role)
    user = _read_user(folder / "user.json")
    if user.role != role:
        raise BusCredentialsError(f"the bus credentials in {folder} are the {user.role}'s, not the {role}'s")
    if run is not None and user.run != run:
        raise BusCredentialsError(f"the bus credentials in {folder} are for run {user.run!r}, this service runs "
                                  f"{run!r} (make them with `curlnav bus credentials --run {run} --out DIR`)")
    return user


def load_router(path: str | Path) -> RouterAuth:
    """The router's dictionary file, access control and own user from ``path``."""
    user = load_user(path, "router")
    folder = _role_folder(path, "router")
    try:
        acl = json.loads((folder / "acl.json").read_text())
    except (OSError, ValueError) as exc:
        raise BusCredentialsError(f"unreadable access control {folder / 'acl.json'}: {exc}") from None
    if not (folder / "users.txt").is_file():
        raise BusCredentialsError(f"no user dictionary {folder / 'users.txt'}")
    return RouterAuth((folder / "users.txt").resolve(), acl, user)


def acl_table() -> str:
    """``allowed`` as text, one role a line, keys under ``curlnav/<run>/`` (``curlnav bus credentials`` prints it)."""
    names = {PUT: "put", SUBSCRIBE: "sub", QUERY: "get", QUERYABLE: "answer", TOKEN: "token", WATCH: "watch"}
    return "\n".join(f"  {role:<9} " + ", ".join(f"{names[m]} {k}" for m, k in allowed(role)) for role in ALLOWED)
