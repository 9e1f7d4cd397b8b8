"""One bus identity per actor replica: each replica claims one ``actor-<n>`` of the run's credentials.

``curlnav bus credentials --actors N`` mints ``actor-0`` .. ``actor-<N-1>`` (the declared maximum of
replicas), each a bus user the router lets put only under its own id. Replicas made by
``docker compose --scale`` cannot be told apart at start, so each one *claims* an identity:

* **Compose (one host)**: every replica mounts the same folder of identities (the ``bus-actors``
  volume) and takes the first ``actor-<n>`` whose folder no live process holds an exclusive
  ``flock`` on. The lock is held for the process's life and the kernel drops it when the process
  (or its container) dies, so a restarted replica takes a free identity again; no lock file is
  written, so the folder may be mounted read-only. Locks are seen by every process of one kernel:
  the identities of one host's replicas, not across hosts.
* **An explicit id** (``--actor-id actor-<n>``, or an actor given only the folder ``actor-<n>``) takes
  the same lock (``hold_actor_identity``): an identity never runs twice at once, whichever way it
  was named, and a claim never takes one an explicit id holds.
* **Swarm (several hosts)**: ``slot`` (``CURLNAV_ACTOR_SLOT={{.Task.Slot}}``, 1-based, unique in the
  service and kept when Swarm replaces a task) names the identity, ``actor-<slot-1>``; it is locked
  as well, so two processes of one container cannot both use it.

When every identity is held, or the slot has none, the claim fails with one line that says how
to mint more (``IdentitiesExhausted``).
"""

from __future__ import annotations

import fcntl
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from curlnav.bus.security import BusCredentialsError, is_actor_name

#: what a user does when the identities run out (compose; elsewhere ``curlnav bus credentials --actors N``)
MORE = "raise CURLNAV_MAX_ACTORS and re-run the credentials service (or `curlnav bus credentials --actors N`)"


class IdentitiesExhausted(BusCredentialsError):
    """Every actor identity of the folder is held by a live process (or the slot has none)."""


@dataclass
class ActorIdentity:
    """An identity this process holds: ``name`` (``actor-<index>``), its credentials ``folder``
    and the open descriptor of the folder that carries the lock (closed: released)."""

    name: str
    index: int
    folder: Path
    fd: int = field(repr=False)

    def release(self) -> None:
        """Give the identity back (the process's exit does the same)."""
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
            _HELD.pop(str(self.folder), None)


#: identities this process holds (by folder), kept referenced so that their locks live as long as the process
_HELD: dict[str, ActorIdentity] = {}


def actor_identities(folder: str | Path) -> list[str]:
    """The ``actor-<n>`` identities minted in ``folder`` (those with a ``user.json``), by number."""
    folder = Path(folder)
    names = [p.name for p in folder.glob("actor-*") if is_actor_name(p.name) and (p / "user.json").is_file()]
    return sorted(names, key=lambda name: int(name.split("-")[1]))


def _try_lock(folder: Path) -> int | None:
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    except BaseException:
        os.close(fd)
        raise
    return fd


def claim_actor_identity(folder: str | Path, slot: int | None = None) -> ActorIdentity:
    """Claim one actor identity of ``folder`` for this process's life: the first free one, or,
    with ``slot`` (1-based, Swarm's ``{{.Task.Slot}}``), ``actor-<slot-1>``. Raises
    ``IdentitiesExhausted`` when none is free (or the slot's is missing or held)."""
    folder = Path(folder)
    names = actor_identities(folder)
    if not names:
        raise BusCredentialsError(f"no actor identities (actor-<n>/user.json) in {folder}: make them with "
                                  f"`curlnav bus credentials --actors N --out DIR`")
    if slot is not None:
        name = f"actor-{slot - 1}"
        if slot < 1 or name not in names:
            raise IdentitiesExhausted(f"actor slot {slot} has no identity: {len(names)} actor identities are minted "
                                      f"in {folder} ({names[0]} .. {names[-1]}); {MORE}")
        candidates = [name]
    else:
        candidates = names
    for name in candidates:
        if str(folder / name) in _HELD:
            continue
        fd = _try_lock(folder / name)
        if fd is not None:
            _HELD[str(folder / name)] = identity = ActorIdentity(name, int(name.split("-")[1]), folder / name, fd)
            return identity
    if slot is not None:
        raise IdentitiesExhausted(f"actor identity {candidates[0]} (slot {slot}) is in use by another process")
    raise IdentitiesExhausted(f"all {len(names)} actor identities are in use; {MORE}")


def hold_actor_identity(folder: str | Path, name: str) -> ActorIdentity | None:
    """Take the lock of actor identity ``name``, named explicitly (``--actor-id``): ``folder/name``
    (a folder of identities) or ``folder`` itself (that actor's own folder), as a claim takes it.
    None when ``folder`` holds no such identity (an id never minted, the shared actor user): there
    is nothing to lock. Raises ``IdentitiesExhausted`` when another process holds it; one this
    process holds already is returned."""
    folder = Path(folder)
    if (folder / name / "user.json").is_file():
        target, hint = folder / name, "give this actor another --actor-id, or none to claim a free one"
    elif (folder / "user.json").is_file() and _user_of(folder) == name:
        target, hint = folder, "give this actor another identity's folder"
    else:
        return None
    if str(target) in _HELD:
        return _HELD[str(target)]
    fd = _try_lock(target)
    if fd is None:
        raise IdentitiesExhausted(f"actor identity {name} is in use by another process ({target}): each identity "
                                  f"runs once; {hint}")
    index = int(name.split("-")[1]) if is_actor_name(name) else -1
    _HELD[str(target)] = identity = ActorIdentity(name, index, target, fd)
    return identity


def _user_of(folder: Path) -> str:
    try:
        return str(json.loads((folder / "user.json").read_text()).get("user", ""))
    except (OSError, ValueError, AttributeError):
        return ""
