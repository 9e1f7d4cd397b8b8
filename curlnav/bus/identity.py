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
* **Swarm (several hosts)**: ``slot`` (``CURLNAV_ACTOR_SLOT={{.Task.Slot}}``, 1-based, unique in the
  service and kept when Swarm replaces a task) names the identity, ``actor-<slot-1>``; it is locked
  as well, so two processes of one container cannot both use it.

When every identity is held, or the slot has none, the claim fails with one line that says how
to mint more (``IdentitiesExhausted``).
"""

from __future__ import annotations

import fcntl
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from curlnav.bus.security import BusCredentialsError

ACTOR_NAME = re.compile(r"actor-(\d+)")
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
    names = [p.name for p in folder.glob("actor-*") if ACTOR_NAME.fullmatch(p.name) and (p / "user.json").is_file()]
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
