"""``curlnav worlds``: generate, show, scatter-balls, rank and import-sdf worlds (``add_commands``)."""

from __future__ import annotations

import argparse
from pathlib import Path


def parse_params(items: list[str] | None) -> dict:
    """``--param KEY=VALUE`` items as generator keyword arguments (ints, or floats when the value has
    a ``.`` or an ``e``); ``ValueError`` (one line) for an item without ``=``."""
    params = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--param takes KEY=VALUE, got {item!r}")
        params[key.replace("-", "_")] = float(value) if any(ch in value for ch in ".e") else int(value)
    return params


def _cmd_generate(args: argparse.Namespace) -> int:
    from curlnav.worlds.core.world import save_world
    from curlnav.worlds.families import generate

    out = Path(args.out)
    for seed in range(args.seed, args.seed + args.count):
        world = generate(args.family, seed, **parse_params(args.param))
        path = save_world(world, out / f"{world.name}.yaml")
        print(f"{path}: {world.size[0]:.1f} m x {world.size[1]:.1f} m, {len(world.pairs)} pairs, "
              f"{len(world.balls)} balls, {len(world.doors)} doors")
    return 0


def _cmd_show(args: argparse.Namespace) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from curlnav.worlds.builtin import get_world
    from curlnav.worlds.core.picture import draw_world
    from curlnav.worlds.difficulty.rank import measure, measured_pairs, path_points, world_paths

    world = get_world(args.world)
    pairs = measured_pairs(world)
    _, paths = world_paths(world)
    d = measure(world)
    x0, y0, x1, y1 = world.bounds
    fig, ax = plt.subplots(figsize=(8, 8 * (y1 - y0) / max(x1 - x0, 1e-9) + 0.6), dpi=110)
    draw_world(ax, world, pairs=pairs)
    for path in paths:
        ax.plot(*path_points(world, path), "-", lw=1, color="tab:green")
    ax.set_title(f"{world.name}: Dist {d.distance:.2f}  Vis {d.visibility:.2f}  Disp {d.dispersion:.2f}  "
                 f"CD {d.characteristic_dimension:.2f}  Tor {d.tortuosity:.2f}", fontsize=9)
    out = Path(args.out or f"runs/worlds/{world.name}.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    drawn = "" if world.pairs else " (seeded random: the map has none)"
    print(f"{world.name}: {world.size[0]:.1f} m x {world.size[1]:.1f} m, {len(pairs)} pairs{drawn}; picture: {out}")
    return 0


def _cmd_scatter_balls(args: argparse.Namespace) -> int:
    from curlnav.worlds.builtin import get_world
    from curlnav.worlds.core.world import save_world
    from curlnav.worlds.procedural.scatter import scatter_balls

    world = get_world(args.world)
    out = Path(args.out)
    if out.suffix not in (".yaml", ".yml"):
        raise ValueError(f"--out must be a world YAML path (.yaml), got {args.out!r}")
    task = scatter_balls(world, args.count, seed=args.seed, radius=args.radius, mass=args.mass, pairs=args.pairs)
    path = save_world(task.with_changes(name=out.stem), out)
    print(f"{path}: {len(task.balls) - len(world.balls)} balls on the shortest paths of {len(task.pairs)} pairs "
          f"({', '.join(p.name for p in task.pairs)}) of {world.name}")
    return 0


def _cmd_rank(args: argparse.Namespace) -> int:
    import time

    from curlnav.worlds.builtin import get_world
    from curlnav.worlds.difficulty.rank import rank, ranking_table, write_outputs

    worlds = [get_world(spec) for spec in args.worlds]
    t0 = time.perf_counter()
    rows = rank(worlds)
    elapsed = time.perf_counter() - t0
    print(ranking_table(rows))
    files = write_outputs(rows, args.out)
    print(f"measured {len(worlds)} worlds in {elapsed:.2f} s; wrote {files['csv']}, {files['json']}, {files['png']}")
    return 0


def _cmd_import_sdf(args: argparse.Namespace) -> int:
    from curlnav.worlds.real.sdf import import_sdf

    out, world, contents = import_sdf(args.world, args.out, args.resolution, args.margin, args.skip_unsupported)
    kinds = [s.kind for s in contents.shapes]
    rows, cols = world.occupancy.shape
    print(f"{out}: {kinds.count('box')} boxes and {kinds.count('cylinder')} cylinders of {args.world} on {cols} x {rows} "
          f"cells of {world.resolution:g} m ({world.size[0]:.2f} m x {world.size[1]:.2f} m, origin "
          f"({world.origin[0]:g}, {world.origin[1]:g}))")
    print("start/goal pairs: none of its own, so curlnav eval, train and rollout draw seeded random ones on its free "
          "space (as on a SLAM map); for fixed ones add 'pairs: [{name: p1, x: X, y: Y, yaw: 0, gx: GX, gy: GY}]' to "
          "the YAML (docs/guide/worlds.md), or let curlnav worlds scatter-balls write drawn ones with balls on "
          "their paths")
    if contents.unsupported:
        listed, more = contents.unsupported[:10], len(contents.unsupported) - 10  # each item is a short name
        print(f"skipped {len(contents.unsupported)} unsupported: {', '.join(listed)}{f' and {more} more' * (more > 0)}")
    return 0


def _cmd_export_map(args: argparse.Namespace) -> int:
    """A world's walls as a ``map_server`` map (YAML + PGM), as a robot team's SLAM map would be."""
    from curlnav.worlds.builtin import get_world
    from curlnav.worlds.core.world import save_world

    out = Path(args.out)
    if out.suffix not in (".yaml", ".yml"):
        raise ValueError(f"--out {args.out}: a map's YAML file ends in .yaml")
    doors_out = Path(args.doors_out) if args.doors_out else None
    if doors_out is not None and doors_out.suffix not in (".yaml", ".yml"):
        raise ValueError(f"--doors-out {args.doors_out}: a doors file ends in .yaml")
    world = get_world(args.world)
    if doors_out is not None and not world.doors:
        raise ValueError(f"--doors-out: {world.name} has no doors")
    save_world(world, out, map_only=True)
    rows, cols = world.occupancy.shape
    print(f"wrote {out} and {out.with_suffix('.pgm').name}: the walls of {world.name}, {cols} x {rows} cells of "
          f"{world.resolution:g} m; no pairs, balls or doors (train --world {out} draws its pairs; --doors marks doors)")
    if doors_out is not None:
        from curlnav.worlds.real.own_map import doors_text

        doors_out.write_text(doors_text(world.doors))
        print(f"wrote {doors_out}: its {len(world.doors)} doors, as a team marks them (train --doors {doors_out})")
    return 0


def add_commands(sub) -> None:
    """``worlds generate|show|scatter-balls|rank|import-sdf``; the families in ``generate``'s help come from
    ``curlnav.worlds.families.FAMILIES``."""
    from curlnav.worlds.families import FAMILIES

    worlds = sub.add_parser("worlds", help="generate, draw and rank worlds")
    worlds_sub = worlds.add_subparsers(dest="worlds_command", required=True)
    p = worlds_sub.add_parser("generate", help="write generated worlds as world files")
    p.add_argument("family", help=", ".join(FAMILIES))
    p.add_argument("--seed", type=int, default=0, help="seed of the first world")
    p.add_argument("--count", type=int, default=1, help="worlds with seeds seed, seed+1, ...")
    p.add_argument("--param", action="append", help="generator parameter KEY=VALUE (e.g. fill_pct=0.3)")
    p.add_argument("--out", default="worlds", help="folder for the world files")
    p.set_defaults(func=_cmd_generate)
    p = worlds_sub.add_parser("show", help="draw a world with its pairs and their shortest paths")
    p.add_argument("world", help="built-in name, world YAML, or FAMILY:SEED")
    p.add_argument("--out", default=None, help="PNG path")
    p.set_defaults(func=_cmd_show)
    p = worlds_sub.add_parser("scatter-balls", help="a NAMO task from any map: balls on the shortest paths of its pairs")
    p.add_argument("world", help="built-in name, world YAML (e.g. a plain ROS SLAM map), or FAMILY:SEED")
    p.add_argument("--count", type=int, default=6, help="balls to add")
    p.add_argument("--seed", type=int, default=0, help="seed of the random pairs (plain maps) and of the places")
    p.add_argument("--pairs", type=int, default=3, help="random pairs to draw when the map has none")
    p.add_argument("--radius", type=float, default=0.25, help="ball radius (m)")
    p.add_argument("--mass", type=float, default=0.5, help="ball mass (kg)")
    p.add_argument("--out", required=True, help="world YAML to write (its image is written beside it)")
    p.set_defaults(func=_cmd_scatter_balls)
    p = worlds_sub.add_parser("export-map", help="a world's walls as a map_server map (YAML + PGM), as a SLAM map is")
    p.add_argument("world", help="built-in name, world YAML, or FAMILY:SEED")
    p.add_argument("--out", required=True, help="the map's YAML (its PGM is written beside it)")
    p.add_argument("--doors-out", metavar="FILE.yaml", help="also write the world's doors as a doors file (train --doors)")
    p.set_defaults(func=_cmd_export_map)
    p = worlds_sub.add_parser("rank", help="Table I and the MDS picture for a set of worlds")
    p.add_argument("worlds", nargs="+", help="built-in names, world YAMLs, or FAMILY:SEED")
    p.add_argument("--out", default="runs/ranking", help="folder for the table (CSV, JSON) and the picture")
    p.set_defaults(func=_cmd_rank)
    p = worlds_sub.add_parser("import-sdf", help="a Gazebo world's static boxes and cylinders as a world file",
                              description="Reads the static boxes and cylinders of a Gazebo SDF world (nested "
                                          "model, link and collision poses composed) onto an occupancy grid. What "
                                          "it cannot represent (meshes, heightmaps, spheres, planes other than the "
                                          "ground, tilted shapes, non-static models, includes) is named and "
                                          "refused (exit 2), or dropped with --skip-unsupported.")
    p.add_argument("world", help="the SDF file (.world or .sdf, or either xz-compressed: .world.xz)")
    p.add_argument("--out", default=None, help="world YAML to write, its image beside it (default: WORLD.yaml beside the SDF)")
    p.add_argument("--skip-unsupported", action="store_true", help="drop what cannot be represented, naming it")
    p.add_argument("--resolution", type=float, default=0.025, help="m per cell (default 0.025: a 0.075 m cylinder "
                                                                   "is 6 cells across)")
    p.add_argument("--margin", type=float, default=1.0, help="m of free space around the shapes (default 1)")
    p.set_defaults(func=_cmd_import_sdf)
