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
their own, so an actor never holds the learner's password; ``host_credentials`` writes what one
host needs and nothing more (``curlnav bench hosts``). The evaluator uses HTTP only.

What ``make_credentials`` keeps from an earlier call is checked first: actor identities are
``actor-<n>`` only (n a number, no wildcard that would become an access-control rule for many
ids), and it never reads or writes through a symbolic link (a link planted in DIR would make it
write and chmod elsewhere): anything else is refused with one line that names it.
"""

from __future__ import annotations

import errno
import json
import os
import re
import secrets
import stat
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


#: an actor identity's name: ``actor-<n>``, n a number as ``str(int)`` writes it (no sign, no leading zero,
#: ASCII digits): Zenoh would read any other character of a user name (``$*``, ``*``) into its ACL rule
ACTOR_NAME = re.compile(r"actor-(0|[1-9][0-9]{0,8})")


def actor_ids(count: int) -> list[str]:
    """The actor identities minted for ``count`` replicas: ``actor-0`` .. ``actor-<count-1>``."""
    return [f"actor-{i}" for i in range(count)]


def is_actor_name(name: str) -> bool:
    """Whether ``name`` is an actor identity, ``actor-<n>`` (``ACTOR_NAME``)."""
    return ACTOR_NAME.fullmatch(name) is not None
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
    bad = [actor for actor in actors if not is_actor_name(actor)]
    if bad:  # its name would become the key of its rule: "actor-$*" may put under every actor's id
        raise BusCredentialsError(f"{bad[0][:60]!r} is not an actor identity (actor-<n>, n a number)")
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


def _not_a_link(path: Path) -> None:
    """Refuse ``path`` if it is a symbolic link (one planted in DIR would redirect a write or a chmod)."""
    if path.is_symlink():
        raise BusCredentialsError(f"{path} is a symbolic link: bus credentials are never read or written through "
                                  f"a link; remove it")


def _open_private(path: Path, flags: int, mode: int = 0o600) -> int:
    """``os.open`` that never follows a symbolic link at ``path`` itself (``O_NOFOLLOW``)."""
    try:
        return os.open(path, flags | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, mode)
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.ENOTDIR) and path.is_symlink():
            _not_a_link(path)
        raise


def _read_private(path: Path) -> str:
    """The text of the regular file ``path``, never through a link (missing: ``FileNotFoundError``)."""
    fd = _open_private(path, os.O_RDONLY)
    with os.fdopen(fd) as f:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise BusCredentialsError(f"{path} is not a regular file; remove it")
        return f.read()


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` (mode 0600, atomically), unless it already holds it; never
    through a link (a link at ``path`` is refused, the new file replaces only the name)."""
    try:
        fd = _open_private(path, os.O_RDONLY)
    except FileNotFoundError:
        fd = -1
    if fd >= 0:
        with os.fdopen(fd) as f:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise BusCredentialsError(f"{path} is not a regular file; remove it")
            if f.read() == text:
                os.fchmod(fd, 0o600)
                return
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.unlink(missing_ok=True)  # a link there is removed, not followed
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    with os.fdopen(fd, "w") as f:
        os.fchmod(f.fileno(), 0o600)
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _private_dir(path: Path) -> Path:
    """``path`` as a real folder, mode 0700 (made if missing; a link there is refused, never chmodded)."""
    _not_a_link(path)
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    fd = _open_private(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fchmod(fd, 0o700)
    finally:
        os.close(fd)
    return path


def _read_user(path: Path, follow: bool = True) -> BusUser:
    """The user of ``path``; ``follow=False`` (``make_credentials``): never through a link."""
    try:
        d = json.loads(path.read_text() if follow else _read_private(path))
        return BusUser(str(d["role"]), str(d["user"]), str(d["password"]), str(d["run"]))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        if isinstance(exc, BusCredentialsError):
            raise
        raise BusCredentialsError(f"unreadable bus credentials {path}: {exc}") from None


def _actor_folders(out: Path) -> list[str]:
    """The actor identities already in ``out``: every entry named ``actor-...`` must be a real
    folder named ``actor-<n>`` (those without a ``user.json`` are not identities yet)."""
    names = []
    for entry in sorted(os.scandir(out), key=lambda e: e.name):
        if not entry.name.startswith("actor-"):
            continue
        path = out / entry.name
        if not is_actor_name(entry.name):
            raise BusCredentialsError(f"{path} is not an actor identity (actor-<n>, n a number): bus credentials "
                                      f"never mint it; remove it")
        _not_a_link(path)
        if not entry.is_dir(follow_symlinks=False):
            raise BusCredentialsError(f"{path} is not a folder; remove it")
        user = path / "user.json"
        _not_a_link(user)
        if user.exists():
            names.append(entry.name)
    return sorted(names, key=lambda name: int(name.split("-")[1]))


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
    out = Path(out)  # DIR itself is the user's choice (it may be a link); nothing below it may be
    out.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(out, 0o700)
    for name in (*ROLES, SHARED_ACTOR, "tls"):  # what is kept from before is checked before anything is written
        _not_a_link(out / name)
    kept = _actor_folders(out)
    actor_names = sorted(set(actor_ids(actors)) | set(kept), key=lambda name: int(name.split("-")[1]))
    names = [*ROLES, *actor_names, *([SHARED_ACTOR] if shared_actor else [])]
    users, done = {}, {}
    for name in names:
        role = "actor" if name in actor_names or name == SHARED_ACTOR else name
        path = _private_dir(out / name) / "user.json"
        _not_a_link(path)
        try:
            user = _read_user(path, follow=False)
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
    acl = access_control(run, actor_names, shared_actor or (out / SHARED_ACTOR / "user.json").exists(),
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

    for path in folder.iterdir():  # the CA's key and every certificate: never read or written through a link
        _not_a_link(path)
    try:
        ca_key = serialization.load_pem_private_key(_read_private(folder / "ca.key").encode(), None)
        ca = x509.load_pem_x509_certificate(_read_private(folder / "ca.pem").encode())
    except (OSError, ValueError) as exc:
        if isinstance(exc, BusCredentialsError):
            raise
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


def host_credentials(source: str | Path, dest: str | Path, users: list[str] | tuple[str, ...],
                     router: str = "") -> Path:
    """Write into ``dest`` what one host needs of the run's credentials ``source`` and nothing
    more: the folder of each of ``users`` (the ``router``'s holds its dictionary and access control
    too) and, with ``router`` (its name in ``source/tls``), ``dest/router/tls/`` with the CA's
    certificate and that router's own certificate and key, never the CA's key nor another
    router's. Each service is then given its own ``dest/<user>`` (``load_router`` and ``load_tls``
    read ``dest/router``). The router's dictionary keeps only the users it authenticates: ``users``
    (its host's services) and ``router`` (the other routers' links), so a host never holds another
    host's services' passwords. Returns ``dest``."""
    source, dest = Path(source), _private_dir(Path(dest))
    admitted = {*users, "router"}
    for user in users:
        folder = source / user
        _not_a_link(folder)
        for path in sorted(folder.iterdir()):
            if path.name.startswith("."):
                continue  # an interrupted write's temporary file
            text = _read_private(path)
            if user == "router" and path.name == "users.txt":
                text = "".join(line for line in text.splitlines(keepends=True)
                               if line.split(":", 1)[0] in admitted)
            _write_private(_private_dir(dest / user) / path.name, text)
    if router:
        for name in ("ca.pem", f"{router}.pem", f"{router}.key"):
            _write_private(_private_dir(dest / "router" / "tls") / name, _read_private(source / "tls" / name))
    return dest


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
