"""The registry of world families: the one list every reader takes their names from.

A family is a generator ``def my_family(seed=0, **params) -> World`` named by its entry point
(``"module:function"``), imported only when a world of it is made, so reading the names (the
``worlds generate`` help, a curriculum check) costs nothing. Readers: ``generate`` below, the
``FAMILY:SEED`` resolver (``curlnav.worlds.builtin.get_world``), world distributions
(``curlnav.worlds.distribution``: the parameters a family takes) and ``curlnav worlds generate``.
Every family's seeds from ``curlnav.worlds.core.heldout.HELD_OUT_FROM`` upward are held out.

To add a family: write its generator (a module in ``curlnav/worlds/procedural/``, or a function in
its ``generators.py``) and add one ``Family`` line to ``FAMILIES``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from curlnav.worlds.core.world import World


@dataclass(frozen=True)
class Family:
    """A world family: its generator's entry point ``"package.module:function"`` and one line about it."""

    entry_point: str
    about: str = ""

    def load(self) -> Callable[..., World]:
        """The generator function (imports its module)."""
        module, _, name = self.entry_point.partition(":")
        return getattr(importlib.import_module(module), name)

    def __call__(self, seed: int = 0, **params) -> World:
        return self.load()(seed=seed, **params)


FAMILIES: dict[str, Family] = {
    "barn": Family("curlnav.worlds.procedural.generators:barn", "the BARN benchmark's cellular automaton"),
    "barn-course": Family("curlnav.worlds.barn_challenge.barn_course:barn_course",
                          "BARN grids set in the BARN Challenge's layout "
                          "(cylinders, start area, Jackal start and goal): training worlds for its suite"),
    "barn-3x3": Family("curlnav.worlds.procedural.generators:barn_3x3",
                       "3 x 3 BARN blocks scaled to 36 m, 8 balls re-placed every reset"),
    "t-maze": Family("curlnav.worlds.procedural.generators:t_maze", "five rooms in a T joined by hinged doors and narrow gates, "
                     "one ball per room, curriculum pairs p1..p4"),
    "dead-end": Family("curlnav.worlds.procedural.generators:dead_end",
                       "a U-shaped wall between start and goal, its mouth towards the start (a trap without memory)"),
    "cave": Family("curlnav.worlds.procedural.generators:cave", "wide winding tunnels carved by random walkers (SubT-like)"),
    "forest": Family("curlnav.worlds.procedural.generators:forest", "an open field of trees at a given density"),
    "garage": Family("curlnav.worlds.procedural.generators:garage", "a pillared parking hall with a few partition walls"),
    "indoor": Family("curlnav.worlds.procedural.generators:indoor", "long corridors joining lobbies, rooms on both sides"),
    "office": Family("curlnav.worlds.procedural.generators:office", "a smaller, tighter indoor"),
    "campus": Family("curlnav.worlds.procedural.generators:campus", "building blocks on a street grid, courtyards and plazas"),
    "auditorium": Family("curlnav.worlds.procedural.generators:auditorium",
                         "arcs of seating around a stage, entered through a corridor"),
    "slam-office": Family("curlnav.worlds.procedural.slam_like:slam_office", "a large office floor as a SLAM stack maps it "
                          "(0.05 m cells, ragged walls, furniture, noise)"),
    "slam-floor": Family("curlnav.worlds.procedural.slam_like:slam_floor", "a NAMO office floor of real widths as a SLAM map"),
    "slam-namo-office": Family("curlnav.worlds.procedural.slam_like:slam_namo_office", "namo-office degraded as a SLAM map"),
    "slam-namo-indoor": Family("curlnav.worlds.procedural.slam_like:slam_namo_indoor", "namo-indoor degraded as a SLAM map"),
    "slam-namo-auditorium": Family("curlnav.worlds.procedural.slam_like:slam_namo_auditorium",
                                   "namo-auditorium degraded as a SLAM map"),
    "t-maze-doors": Family("curlnav.worlds.procedural.tmaze:t_maze_doors", "T-Mazes that vary, whose pairs must push doors open"),
    "namo-auditorium": Family("curlnav.worlds.procedural.namo:namo_auditorium", "unseen NAMO world: a lobby, doors, a hall"),
    "namo-office": Family("curlnav.worlds.procedural.namo:namo_office", "unseen NAMO world: rooms off a corridor through doors"),
    "namo-indoor": Family("curlnav.worlds.procedural.namo:namo_indoor", "unseen NAMO world: 3 x 3 rooms joined by doors"),
}


def generate(family: str, seed: int = 0, **params) -> World:
    """A world of ``family``; unknown families and parameters raise ``ValueError``."""
    if family not in FAMILIES:
        raise ValueError(f"unknown world family {family!r}; choose from {', '.join(FAMILIES)}")
    try:
        return FAMILIES[family](seed=seed, **params)
    except TypeError as exc:
        raise ValueError(f"bad parameters for {family}: {exc}") from None
