"""Every role of the navigation stack, and every entry each role may name.

A navigation stack (``curlnav.nav.stack.NavStack``) names one entry per role; the builder
(``curlnav.nav.build.build_stack``) makes each from its class, innermost first, and hands each the
one it wraps. The roles, as Nav2 has them (``nav2_core``: GlobalPlanner, Controller, Behavior, the
collision monitor beside them), innermost first:

- ``controller``: turns the observation into the command (a trained policy, ``dwa``, ``tare-l``,
  the ``oracle``);
- ``global_planner``: sets the controller's goal to a waypoint on a plan (A* on the true map, or on
  a map of the robot's own scans);
- ``recovery``: drives instead of the controller while it makes no progress (the rescue);
- ``safety``: checks each command against the scan before it goes out (the shield);
- ``perception``: rewrites what every role behind it sees (the label vote, laser odometry), in a
  fixed order, the last one outermost.

An entry is its class (``"module:Class"``, imported only when a stack names it, so ``curlnav --help``
does not pay for the planners) and its settings: sections, each a frozen config dataclass handed to
the class as one keyword argument. To add an entry: its module and one ``register(Entry(...))``
line here. This module imports nothing of the roles, so every role may import it.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import import_module

#: the roles, innermost (the controller) first, as ``build_stack`` wraps them
ROLES = ("controller", "global_planner", "recovery", "safety", "perception")

#: the shorthand suffixes of an agent argument (``POLICY+rescue+shield``), each naming one entry
GLOBAL_PLAN_SUFFIX = "+global-plan"
SCAN_PLAN_SUFFIX = "+scan-plan"
RESCUE_SUFFIX = "+rescue"
SHIELD_SUFFIX = "+shield"
TRACK_SUFFIX = "+track"
SCAN_MATCH_SUFFIX = "+scan-match"
#: after a policy artefact: the network alone, without the helpers its metadata ships it with
BARE_SUFFIX = "+bare"

#: the entry a policy artefact or checkpoint is, as a controller (its one setting: ``path``)
POLICY_ENTRY = "policy"


def load_attribute(entry_point: str):
    """The object ``"package.module:Name"`` names (its module imported now)."""
    module, _, attr = entry_point.partition(":")
    return getattr(import_module(module), attr)


@dataclass(frozen=True)
class Entry:
    """One entry of a role: ``name`` in a stack, ``entry_point`` its class (``"module:Class"``),
    ``sections`` its settings: ``(section, keyword, "module:ConfigClass")``, each config handed to
    the class as ``keyword=``. ``map_less``: it sees only what a policy sees (scan, labels, goal)
    and odometry, so it runs on a robot; ``suffix``: its shorthand in an agent argument."""

    role: str
    name: str
    entry_point: str
    about: str
    map_less: bool = True
    sections: tuple[tuple[str, str, str], ...] = ()
    suffix: str = ""

    def load(self) -> type:
        """The entry's class (its module imported now)."""
        return load_attribute(self.entry_point)

    def config_classes(self) -> dict[str, type]:
        """section -> its config dataclass (their modules imported now)."""
        return {section: load_attribute(config) for section, _, config in self.sections}


#: role -> entry name -> entry, in the order the help lists them
ENTRIES: dict[str, dict[str, Entry]] = {role: {} for role in ROLES}
#: old names still taken, -> the controller they name
ALIASES = {"planner": "oracle"}


def register(entry: Entry) -> Entry:
    """Add ``entry`` to its role (a name given twice in one role is refused)."""
    if entry.role not in ENTRIES:
        raise ValueError(f"{entry.name}: no role {entry.role!r}; roles: {', '.join(ROLES)}")
    if entry.name in ENTRIES[entry.role] or (entry.role == "controller" and entry.name in ALIASES):
        raise ValueError(f"a {entry.role} named {entry.name!r} is registered already")
    if entry.name != POLICY_ENTRY and ":" not in entry.entry_point:
        raise ValueError(f"{entry.name}: entry point {entry.entry_point!r} is not 'module:Class'")
    ENTRIES[entry.role][entry.name] = entry
    return entry


_SCAN_FILTER = ("scan_filter", "scan_filter", "curlnav.nav.perception.scan_filter:ScanFilterConfig")
_PUSH = ("push", "push", "curlnav.nav.safety.push_check:PushConfig")
for _entry in (
    Entry("controller", POLICY_ENTRY, "", "a trained policy: an artefact folder or a checkpoint .safetensors", True),
    Entry("controller", "tare-l", "curlnav.nav.controllers.local:TareLocalPlanner",
          "map-less, after TARE's local planner", True,
          (("tare", "config", "curlnav.nav.controllers.local:TareConfig"), _SCAN_FILTER)),
    Entry("controller", "dwa", "curlnav.nav.controllers.local:DynamicWindowPlanner",
          "map-less dynamic window approach", True,
          (("dwa", "config", "curlnav.nav.controllers.local:DwaConfig"), _SCAN_FILTER)),
    Entry("controller", "oracle", "curlnav.nav.global_planners.oracle:StaticMapPlanner",
          "A* on the true map and pose", False,
          (("planner", "config", "curlnav.nav.global_planners.oracle:PlannerConfig"),)),
    Entry("global_planner", "true-map", "curlnav.nav.global_planners.global_plan:GlobalPlanAgent",
          "waypoints on A* on the true map (a given map and a localised pose)", False,
          (("waypoints", "config", "curlnav.nav.global_planners.global_plan:WaypointConfig"),), GLOBAL_PLAN_SUFFIX),
    Entry("global_planner", "scan-map", "curlnav.nav.global_planners.scan_map:ScanMapPlanAgent",
          "waypoints on A* on a map of the robot's own scans", True,
          (("scan_map", "config", "curlnav.nav.global_planners.scan_map:ScanMapConfig"), _PUSH), SCAN_PLAN_SUFFIX),
    Entry("recovery", "rescue", "curlnav.nav.recovery.rescue:RescuedPolicy",
          "dwa on the scan map (behind a true-map plan: the plan's tracker) drives while the controller stalls",
          True, (("rescue", "config", "curlnav.nav.recovery.rescue:RescueConfig"),), RESCUE_SUFFIX),
    Entry("safety", "shield", "curlnav.nav.safety.shield:ShieldedPolicy",
          "each command's arc checked against the scan (and the map, behind a true-map plan)", True,
          (("shield", "config", "curlnav.nav.safety.shield:ShieldConfig"), _SCAN_FILTER, _PUSH), SHIELD_SUFFIX),
    Entry("perception", "label-vote", "curlnav.nav.perception.label_filter:LabelFilteredPolicy",
          "movable labels voted over the last scans", True,
          (("label_vote", "config", "curlnav.nav.perception.label_filter:LabelFilterConfig"),), TRACK_SUFFIX),
    Entry("perception", "laser-odometry", "curlnav.nav.perception.scan_match:ScanMatchedPolicy",
          "goal and odometry from matching each scan to the last", True,
          (("scan_match", "config", "curlnav.nav.perception.scan_match:ScanMatchConfig"),), SCAN_MATCH_SUFFIX),
):
    register(_entry)

#: the order a stack's perception entries run in, innermost first (the vote sees laser odometry's pose)
PERCEPTION_ORDER = ("label-vote", "laser-odometry")


def entry_of_suffix(suffix: str) -> Entry | None:
    """The entry a shorthand suffix (``+shield``) names, None when none does."""
    for entries in ENTRIES.values():
        for entry in entries.values():
            if entry.suffix and entry.suffix == suffix:
                return entry
    return None


def suffixes() -> list[str]:
    """Every shorthand suffix, in the order an agent argument writes them, then ``+bare``."""
    order = [e.suffix for role in ("global_planner", "recovery", "safety") for e in ENTRIES[role].values()]
    order += [ENTRIES["perception"][name].suffix for name in PERCEPTION_ORDER]
    return [s for s in order if s] + [BARE_SUFFIX]


def planners() -> dict[str, Entry]:
    """The controllers a name alone selects (every one but a policy): ``tare-l``, ``dwa``, ``oracle``."""
    return {name: e for name, e in ENTRIES["controller"].items() if name != POLICY_ENTRY}


def canonical(name: str) -> str | None:
    """The planner ``name`` stands for (an alias resolved), or None when it names no planner."""
    name = ALIASES.get(name, name)
    return name if name in planners() else None
