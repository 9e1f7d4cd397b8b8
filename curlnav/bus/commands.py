"""``curlnav bus credentials``: a run's Zenoh users and access control (``curlnav.bus.security``),
and ``env_default``, the ``CURLNAV_<NAME>`` defaults every deployment option reads."""

from __future__ import annotations

import argparse
import os


def env_default(name: str, default):
    """Deployment settings from ``CURLNAV_<NAME>`` environment variables (containers) or a default."""
    value = os.environ.get(f"CURLNAV_{name.upper()}")
    if value is None:
        return default
    return type(default)(value) if default is not None and not isinstance(default, bool) else value


def _cmd_credentials(args: argparse.Namespace) -> int:
    from curlnav.bus.security import acl_table, make_credentials

    tls = {}
    for item in filter(None, (i.strip() for i in args.tls.split(","))):
        name, _, address = item.partition("=")
        tls[name.strip()] = address.strip()
    done = make_credentials(args.out, args.run, actors=args.actors, shared_actor=args.shared_actor,
                            tls_hosts=tls or None)
    print(f"bus credentials of run {args.run!r} in {args.out}: "
          + ", ".join(f"{role} ({state})" for role, state in done.items()))
    print(f"give `--bus-credentials {args.out}` (CURLNAV_BUS_CREDENTIALS) to every `curlnav serve`, or to each "
          f"service only its own folder {args.out}/<role> (an actor: {args.out}/actor-<n>, which it then is; given "
          f"the folder of every actor-<n>, each actor claims a free one)")
    if tls:
        from curlnav.bus.mesh import router_flags

        print(f"TLS between routers: the run's CA {args.out}/tls/ca.pem (keep {args.out}/tls/ca.key off the hosts); "
              f"start the main host's router with `curlnav serve router {' '.join(router_flags('NAME'))}` and "
              f"every other host's with `curlnav serve router {' '.join(router_flags('NAME', 'MAIN_ADDRESS'))}`")
    print("access control, default deny (keys under curlnav/<run>/):\n" + acl_table())
    return 0


def add_commands(sub) -> None:
    """``bus credentials``."""
    bus = sub.add_parser("bus", help="the bus's security: Zenoh users and access control of a run")
    bus_sub = bus.add_subparsers(dest="bus_command", required=True)
    p = bus_sub.add_parser("credentials", help="write a run's bus credentials: one user per role with a random "
                                              "password, the router's dictionary and access control")
    p.add_argument("--out", required=True, help="folder to write (0700, files 0600); passwords already there are kept")
    p.add_argument("--run", default=env_default("run", "default"), help="the run (Zenoh key prefix) they are for")
    p.add_argument("--actors", type=int, default=env_default("max_actors", 8),
                   help="the declared maximum of actor replicas (CURLNAV_MAX_ACTORS): one user per actor, actor-0 .. "
                        "actor-<N-1>, each allowed to put only under its own id; a replica claims one at start "
                        "(more may be added later; none are removed)")
    p.add_argument("--shared-actor", action="store_true",
                   help="also one user any actor may use, under any actor id (before replicas claimed an identity "
                        "each; kept for runs that rely on it)")
    p.add_argument("--tls", default="", metavar="NAME=ADDRESS,...",
                   help="routers linked over TLS: the run's CA (tls/ca.pem) and a certificate per router name, for "
                        "the address where it listens (an IP or a DNS name)")
    p.set_defaults(func=_cmd_credentials)
