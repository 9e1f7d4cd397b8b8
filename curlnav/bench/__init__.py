"""Every benchmark of curlnav, one module each, and the registry ``curlnav bench`` reads.

``BENCHES`` maps a bench's name (``curlnav bench NAME``) to its module. A bench module has
``HELP`` (one line for ``curlnav bench --help``), ``add_arguments(parser)`` and
``main(args) -> int`` (the exit status), and imports what it measures (torch, PyBullet, Zenoh)
inside its functions, so listing the benches costs nothing. ``curlnav.bench.commands`` makes the
sub-commands from the registry, in this order.

- ``env``: the simulator's steps/s against a bare PyBullet loop;
- ``learner``: D4PG updates/s per preset and variant;
- ``transport``: the replay service under load over a real router;
- ``metrics``: the worlds' difficulty metrics and the BARN parameter grid;
- ``draws``: the episode loop drawing a new world per episode;
- ``actor``: an actor process's steps/s with K environments;
- ``faults``, ``chaos``, ``hosts``: kills, chaos and partitions of a local (or namespaced) run
  (``netns``: the network namespaces ``hosts`` runs in).
"""

BENCHES: dict[str, str] = {
    "env": "curlnav.bench.env",
    "learner": "curlnav.bench.learner",
    "transport": "curlnav.bench.transport",
    "metrics": "curlnav.bench.metrics",
    "draws": "curlnav.bench.draws",
    "actor": "curlnav.bench.actor",
    "faults": "curlnav.bench.faults",
    "chaos": "curlnav.bench.chaos",
    "hosts": "curlnav.bench.hosts",
}

__all__ = ["BENCHES", "actor", "chaos", "commands", "draws", "env", "faults", "hosts", "learner", "metrics", "netns",
           "transport"]
