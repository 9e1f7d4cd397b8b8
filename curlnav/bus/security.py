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
    DIR/<role>/user.json   {"role", "user", "password", "run"}: replay, learner, scheduler
    DIR/actor-<n>/user.json  one per actor (role actor, user actor-<n>): it may put only under its id
    DIR/actor/user.json    only with --shared-actor: one user any actor may use, under any id
    DIR/tls/               with --tls: the run's CA (ca.pem, ca.key) and <router>.pem/.key per router

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
    "actor": ((PUT, "transitions/{id}"), (PUT, "episodes/{id}"), (QUERY, "scheduler/assign"), (SUBSCRIBE, "weights"),
              (QUERY, "weights/latest"), (SUBSCRIBE, "replay/credit")),
}
SERVICE_ROLES = tuple(ALLOWED)
ROLES = ("router", "replay", "learner", "scheduler")  # one bus user each; actors: one per actor (``actor_ids``)
#: actors an unqualified ``curlnav bus credentials`` mints users for (the declared maximum of replicas)
DEFAULT_MAX_ACTORS = 8
#: the one user all actors shared before an identity per actor (``--shared-actor``): it may put under
#: any actor id, so it is minted only on request (compose replicas that cannot tell themselves apart)
SHARED_ACTOR = "actor"


def actor_ids(count: int) -> list[str]:
    """The actor identities minted for ``count`` replicas: ``actor-0`` .. ``actor-<count-1>``."""
    return [f"actor-{i}" for i in range(count)]
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


def allowed(role: str, ident: str = "*") -> tuple[tuple[str, str], ...]:
    """``ALLOWED[role]`` plus what every service does (``ServiceShell``): ask ``config/*/*`` (the
    config agreement), hold ``alive/<role>/<ident>``, and, for ``CONFIG_OWNERS``, answer
    ``config/<role>/<id>``. ``ident``: an actor's own id (its keys ``{id}``); ``*``: any id (the
    shared actor user, the services)."""
    answer = ((QUERYABLE, f"config/{role}/*"),) if role in CONFIG_OWNERS else ()
    own = ident if role == "actor" else "*"
    rows = ALLOWED[role] + answer + ((QUERY, "config/*/*"), (TOKEN, f"alive/{role}/{{id}}"))
    return tuple((message, key.replace("{id}", own)) for message, key in rows)


def identities(actors: list[str] | tuple[str, ...] = (), shared_actor: bool = False) -> dict[str, tuple[str, str]]:
    """bus user -> (role, the id it may act under): the services (any id of their own role), each
    actor of ``actors`` (only its own id) and, with ``shared_actor``, the shared actor user."""
    out = {role: (role, "*") for role in SERVICE_ROLES if role != "actor"}
    out.update({actor: ("actor", actor) for actor in actors})
    if shared_actor:
        out[SHARED_ACTOR] = ("actor", "*")
    return out


def permissions(run: str, actors: list[str] | tuple[str, ...] = ("actor-0",), shared_actor: bool = False,
                ) -> dict[str, dict[tuple[str, str], list[str]]]:
    """bus user -> (flow, message) -> full key expressions it is allowed on (``identities``).
    Ingress (into the router) is ``allowed(role, id)`` itself; egress (to the user) follows from
    it: a subscriber receives puts on its key, a querier replies, a queryable the queries that
    meet its key; a publisher learns the subscribers that meet its key (Zenoh sends a put only
    when it knows of one) and a querier the queryables. Zenoh grants a message when an allowed key
    expression *includes* its key, so an actor's ``transitions/<its id>`` admits no other id."""
    import zenoh

    prefix = Topology(run).prefix
    users = identities(actors, shared_actor)
    rows = {user: [(message, f"{prefix}/{key}") for message, key in allowed(role, ident)]
            for user, (role, ident) in users.items()}
    every = [row for user_rows in rows.values() for row in user_rows]

    def meeting(message: str, key: str) -> set[str]:
        return {k for m, k in every if m == message and zenoh.KeyExpr(k).intersects(zenoh.KeyExpr(key))}

    out = {}
    for user, user_rows in rows.items():
        perms: dict[tuple[str, str], set[str]] = defaultdict(set)
        for message, key in user_rows:
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
        out[user] = {flow_message: sorted(keys) for flow_message, keys in sorted(perms.items()) if keys}
    return out


def access_control(run: str, actors: list[str] | tuple[str, ...] = ("actor-0",), shared_actor: bool = False,
                   router_names: list[str] | tuple[str, ...] = ()) -> dict:
    """The router's ``access_control`` block: default deny, one subject (its username) and one
    policy per bus user; rules shared between users (every actor's common rows) are written once.
    Routers joined with ``--connect`` (the ``router`` user) relay everything of the run, and so,
    with ``router_names`` (TLS between routers), does a router whose certificate from the run's CA
    names one of them (``cert_common_names`` ``router-<name>``: on mutual TLS each side sees the
    other's certificate, while only the side that connects presents a user and password)."""
    rules: dict[tuple, str] = {}
    rule_list, subjects, policies = [], [], []
    for user, perms in permissions(run, actors, shared_actor).items():
        ids = []
        for (flow, message), keys in perms.items():
            shape = (flow, message, tuple(keys))
            if shape not in rules:
                rules[shape] = f"{flow} {message} {len(rules)}"
                rule_list.append({"id": rules[shape], "permission": "allow", "flows": [flow],
                                  "messages": [message], "key_exprs": keys})
            ids.append(rules[shape])
        subjects.append({"id": user, "usernames": [user]})
        policies.append({"id": user, "rules": ids, "subjects": [user]})
    rule_list.append({"id": "router links", "permission": "allow", "flows": ["ingress", "egress"],
                      "messages": list(MESSAGES), "key_exprs": [f"{Topology(run).prefix}/**"]})
    subjects.append({"id": "router", "usernames": ["router"]})
    if router_names:  # the side that connected authenticated no user: its certificate names it
        subjects.append({"id": "router certificates", "cert_common_names": [f"router-{n}" for n in router_names]})
    policies.append({"id": "router", "rules": ["router links"],
                     "subjects": ["router", "router certificates"] if router_names else ["router"]})
    return {"enabled": True, "default_permission": "deny", "rules": rule_list, "subjects": subjects,
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


def _actor_folders(out: Path) -> list[str]:
    return sorted((p.name for p in out.glob("actor-*") if (p / "user.json").is_file()),
                  key=lambda name: (len(name), name))


def make_credentials(out: str | Path, run: str, actors: int = DEFAULT_MAX_ACTORS, shared_actor: bool = False,
                     tls_hosts: dict[str, str] | None = None) -> dict[str, str]:
    """Write (or complete) the bus credentials of ``run`` into ``out``: one user per service role
    and one per actor (``actor-0`` .. ``actor-<actors-1>``, the declared maximum of replicas;
    actors minted before are kept), each with a random password; with ``shared_actor``, also the
    one user any actor may use (``SHARED_ACTOR``, for replicas that cannot tell themselves apart);
    the router's dictionary and access control. ``tls_hosts`` (router name -> address or ""):
    the run's CA and a certificate per router (``make_tls``). Passwords already there are kept
    (``--resume``, a compose restart); the access control is rewritten for ``run``. Returns
    user -> "created" or "kept"."""
    Topology(run)  # a bad run name fails here
    out = _private_dir(Path(out))
    actor_names = sorted(set(actor_ids(actors)) | set(_actor_folders(out)), key=lambda name: (len(name), name))
    names = [*ROLES, *actor_names, *([SHARED_ACTOR] if shared_actor else [])]
    users, done = {}, {}
    for name in names:
        role = "actor" if name in actor_names or name == SHARED_ACTOR else name
        path = _private_dir(out / name) / "user.json"
        try:
            user = _read_user(path)
            done[name] = "kept"
        except BusCredentialsError:
            user, done[name] = BusUser(role, name, secrets.token_urlsafe(24), run), "created"
        if user.role != role or user.user != name:
            raise BusCredentialsError(f"{path} holds the credentials of {user.user}, not of {name}")
        users[name] = BusUser(role, name, user.password, run)
        _write_private(path, json.dumps(users[name].__dict__, indent=1) + "\n")
    router_names = []
    if tls_hosts:
        router_names = make_tls(out / "tls", tls_hosts)
        done.update({f"tls/{name}": "written" for name in tls_hosts})
    _write_private(out / "router" / "users.txt", "".join(f"{u.user}:{u.password}\n" for u in users.values()))
    acl = access_control(run, actor_names, shared_actor or (out / SHARED_ACTOR / "user.json").is_file(),
                         router_names)
    _write_private(out / "router" / "acl.json", json.dumps(acl, indent=1) + "\n")
    return done


def make_tls(folder: str | Path, hosts: dict[str, str], days: int = 3650) -> list[str]:
    """The run's certificate authority (``ca.pem``, its key ``ca.key``: keep it off the hosts) and,
    per router name of ``hosts``, a certificate (``<name>.pem``, ``<name>.key``) signed by it, for
    the server and the client side of mutual TLS: common name ``router-<name>``, subject
    alternative names ``<name>`` and the address (an IP address or a DNS name) where it listens.
    A CA already there is kept (more routers later); certificates are made again. Returns the
    names of every router certificate in the folder."""
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    folder = _private_dir(Path(folder))
    pem = serialization.Encoding.PEM
    now = datetime.datetime.now(datetime.UTC) - datetime.timedelta(minutes=5)

    def key_text(key) -> str:
        return key.private_bytes(pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()).decode()

    try:
        ca_key = serialization.load_pem_private_key((folder / "ca.key").read_bytes(), None)
        ca = x509.load_pem_x509_certificate((folder / "ca.pem").read_bytes())
    except (OSError, ValueError):
        ca_key = ec.generate_private_key(ec.SECP256R1())
        name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"curlnav run CA {secrets.token_hex(4)}")])
        ca = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(ca_key.public_key())
              .serial_number(x509.random_serial_number()).not_valid_before(now)
              .not_valid_after(now + datetime.timedelta(days=days))
              .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
              .add_extension(x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True)
              .sign(ca_key, hashes.SHA256()))
        _write_private(folder / "ca.key", key_text(ca_key))
        _write_private(folder / "ca.pem", ca.public_bytes(pem).decode())
    for host, address in hosts.items():
        if not host or not all(c.isalnum() or c in "-_." for c in host):
            raise BusCredentialsError(f"router name {host[:40]!r}: letters, digits, '-', '_', '.'")
        key = ec.generate_private_key(ec.SECP256R1())
        alt: list[x509.GeneralName] = [x509.DNSName(host)]
        if address:
            try:
                alt.append(x509.IPAddress(ipaddress.ip_address(address)))
            except ValueError:
                alt.append(x509.DNSName(address))
        cert = (x509.CertificateBuilder()
                .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"router-{host}")]))
                .issuer_name(ca.subject).public_key(key.public_key()).serial_number(x509.random_serial_number())
                .not_valid_before(now).not_valid_after(now + datetime.timedelta(days=days))
                .add_extension(x509.SubjectAlternativeName(alt), critical=False)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                      ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
                .sign(ca_key, hashes.SHA256()))
        _write_private(folder / f"{host}.key", key_text(key))
        _write_private(folder / f"{host}.pem", cert.public_bytes(pem).decode())
    return sorted(p.stem for p in folder.glob("*.pem") if p.stem != "ca")


@dataclass(frozen=True)
class TlsFiles:
    """What a router needs for mutual TLS with the other routers of its run."""

    ca: Path
    certificate: Path
    key: Path


def load_tls(path: str | Path, name: str) -> TlsFiles:
    """Router ``name``'s TLS files from a credentials folder (``DIR/tls/``) or the TLS folder itself."""
    folder = Path(path)
    folder = folder / "tls" if (folder / "tls" / "ca.pem").is_file() else folder
    files = TlsFiles((folder / "ca.pem").resolve(), (folder / f"{name}.pem").resolve(),
                     (folder / f"{name}.key").resolve())
    missing = [str(p) for p in (files.ca, files.certificate, files.key) if not p.is_file()]
    if missing:
        raise BusCredentialsError(f"no TLS files for router {name!r}: {', '.join(missing)} (make them with "
                                  f"`curlnav bus credentials --tls {name}=ADDRESS`)")
    return files


def _role_folder(path: str | Path, name: str) -> Path:
    """``path/<name>`` (a run's credentials folder) or ``path`` itself (one user's folder)."""
    path = Path(path)
    if (path / name / "user.json").is_file():
        return path / name
    if (path / "user.json").is_file():
        return path
    raise BusCredentialsError(f"no bus credentials for the {name} in {path} "
                              f"(make them with `curlnav bus credentials --out DIR`)")


def load_user(path: str | Path, role: str, run: str | None = None, ident: str | None = None) -> BusUser:
    """The bus user of ``role`` from ``path``; refused if they belong to another role or run.
    An actor (``ident``: its id) reads its own user ``actor-<n>``; credentials made with
    ``--shared-actor`` (or before there was an identity per actor) give it the shared one."""
    name = role
    if role == "actor" and ident is not None:
        path_ = Path(path)
        name = ident if (path_ / ident / "user.json").is_file() or not (path_ / SHARED_ACTOR / "user.json").is_file() \
            else SHARED_ACTOR
    folder = _role_folder(path, name)
    user = _read_user(folder / "user.json")
    if user.role != role:
        raise BusCredentialsError(f"the bus credentials in {folder} are the {user.role}'s, not the {role}'s")
    if role == "actor" and ident is not None and user.user not in (ident, SHARED_ACTOR):
        raise BusCredentialsError(f"the bus credentials in {folder} belong to actor {user.user!r}, this actor is "
                                  f"{ident!r} (an actor puts only under its own id: give it its own folder, or "
                                  f"--actor-id {user.user})")
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
    return "\n".join(f"  {role:<9} " + ", ".join(f"{names[m]} {k}" for m, k in allowed(role, "<own id>"))
                     for role in ALLOWED)
