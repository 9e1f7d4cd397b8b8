"""The whole topology of a curlnav run: every Zenoh key expression, one line per connection.

All keys live under ``curlnav/<run>/`` so that several runs can share one router.

    actor    --put  TransitionBatch (reliable, BLOCK)-->  transitions/<actor_id>   --> replay
    actor    --put  EpisodeReport   (reliable, BLOCK)-->  episodes/<actor_id>      --> scheduler
    actor    --get  AssignmentRequest -> Assignment  -->  scheduler/assign         <-- scheduler (queryable)
    actor    --token (liveliness)                    -->  alive/actor/<actor_id>   --> scheduler
    learner  --get  SampleRequest -> SampledBatch    -->  replay/sample            <-- replay (queryable)
    learner  --put  Weights         (reliable, BLOCK)-->  weights                  --> actors
    actor    --get  (empty) -> Weights               -->  weights/latest           <-- learner (queryable, late joiners)
    replay   --put  ServiceStatus   (every 1 s)      -->  status/replay            --> scheduler
    replay   --put  ServiceStatus   (every 20 ms)    -->  replay/credit            --> actors (insert credit: pace, don't block)
    learner  --put  ServiceStatus   (every 1 s)      -->  status/learner           --> scheduler
    learner  --put  PriorityUpdate  (reliable, BLOCK)-->  replay/priorities        --> replay (prioritized replay only)
    every service --token (liveliness)               -->  alive/<role>/<id>        --> scheduler
    every service --get  (empty) -> RunConfig        -->  config/<role>/<id>       <-- every service (queryable): a
                                                          joining service refuses to join on a config hash mismatch

HTTP (not Zenoh): scheduler ``/status``, ``/curriculum``, ``/metrics``, ``POST /admin/advance``;
learner ``/policy/latest``, ``/policy/<version>``, ``/healthz``, ``/metrics``; replay and
actors ``/metrics``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

_RUN_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


@dataclass(frozen=True)
class Topology:
    run: str = "default"

    def __post_init__(self) -> None:
        if not _RUN_NAME.match(self.run):
            raise ValueError(f"run name {self.run!r}: use 1-64 letters, digits, '_', '.', '-'")

    @property
    def prefix(self) -> str:
        return f"curlnav/{self.run}"

    def transitions(self, actor_id: str = "*") -> str:
        return f"{self.prefix}/transitions/{actor_id}"

    def episodes(self, actor_id: str = "*") -> str:
        return f"{self.prefix}/episodes/{actor_id}"

    @property
    def assign(self) -> str:
        return f"{self.prefix}/scheduler/assign"

    @property
    def sample(self) -> str:
        return f"{self.prefix}/replay/sample"

    @property
    def credit(self) -> str:
        return f"{self.prefix}/replay/credit"

    @property
    def weights(self) -> str:
        return f"{self.prefix}/weights"

    @property
    def weights_latest(self) -> str:
        return f"{self.prefix}/weights/latest"

    def status(self, role: str = "*") -> str:
        return f"{self.prefix}/status/{role}"

    def alive(self, role: str = "*", ident: str = "*") -> str:
        return f"{self.prefix}/alive/{role}/{ident}"

    @property
    def priorities(self) -> str:
        return f"{self.prefix}/replay/priorities"

    def config(self, role: str = "*", ident: str = "*") -> str:
        return f"{self.prefix}/config/{role}/{ident}"
