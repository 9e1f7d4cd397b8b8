"""Planners that drive the robot without learning, and the registry that names them.

Modules: ``oracle`` (A* on the true map and pose, ``StaticMapPlanner``, and the ``GridPlanner``
behind it), ``global_plan`` (a policy behind an A* path: ``GlobalPlan``, ``GlobalPlanAgent``),
``local`` (the map-less ``tare-l`` and ``dwa``, on the same scan as a policy), and what a robot's
stack puts round any policy: ``scan_map`` (a plan on a map of its own scans, ``+scan-plan``),
``rescue`` (that plan followed by ``dwa`` while the policy stalls, ``+rescue``) and ``shield`` (each
command checked against the scan, ``+shield``); ``push_check`` says when those believe a movable
label near the base (a robot without an arm never does).

``PLANNERS`` names every planner an agent argument may name (``curlnav eval``, ``curlnav
experiment``; the map-less ones also ``curlnav ros2 run``): a ``Planner`` with its class as an
entry point (``"module:Class"``, imported only when used, so ``curlnav --help`` does not pay for
the planners). A planner class takes the environment's ``EnvConfig``, has a ``label`` and is an
``EpisodeAgent``: ``reset(world, pair)`` at the start of an episode, ``act(observation, info) ->
action`` each step (``info["pose"]``: the base's ``(x, y, yaw)``). A map-less one uses nothing else
than the observation and the pose (as odometry): the ROS 2 node calls ``reset(None, None)`` on
each new goal. To add one: a module here and one ``Planner(...)`` line in ``PLANNERS`` (or
``register`` at run time).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from importlib import import_module
from pathlib import Path

from curlnav.files import FileRefused, read_json, shown

__all__ = ["ALIASES", "BARE_SUFFIX", "GLOBAL_PLAN_SUFFIX", "PLANNERS", "Planner", "RESCUE_SUFFIX", "SCAN_MATCH_SUFFIX",
           "SCAN_PLAN_SUFFIX", "SHIELD_SUFFIX", "TRACK_SUFFIX", "agents_help", "canonical", "deploy_notice",
           "deploy_stack", "global_plan", "label_filter", "local", "make_agent", "make_planner", "oracle", "register",
           "rescue", "rescue_settings", "scan_map", "scan_match", "shield"]


@dataclass(frozen=True)
class Planner:
    """A planner by name: ``entry_point`` is ``"package.module:Class"``; ``map_less`` when it sees
    only what a policy sees (scan, labels, goal) and odometry, so it can run on a robot."""

    name: str
    entry_point: str
    about: str
    map_less: bool

    def load(self) -> type:
        """The planner's class (its module imported now)."""
        module, _, attr = self.entry_point.partition(":")
        return getattr(import_module(module), attr)


#: every planner by name, in the order the help lists them
PLANNERS: dict[str, Planner] = {}


def register(planner: Planner) -> Planner:
    """Add ``planner`` to ``PLANNERS`` (a name given twice is refused)."""
    if planner.name in PLANNERS or planner.name in ALIASES:
        raise ValueError(f"a planner named {planner.name!r} is registered already")
    if ":" not in planner.entry_point:
        raise ValueError(f"{planner.name}: entry point {planner.entry_point!r} is not 'module:Class'")
    PLANNERS[planner.name] = planner
    return planner


#: old names still taken
ALIASES = {"planner": "oracle"}
#: appended to a policy argument, puts the policy behind the oracle's A* path (``GlobalPlanAgent``)
GLOBAL_PLAN_SUFFIX = "+global-plan"
#: appended to a policy argument, puts the policy behind the safety shield (``curlnav.planners.shield``)
SHIELD_SUFFIX = "+shield"
#: appended to a policy argument, puts the policy behind a plan on a map of its own scans (``curlnav.planners.scan_map``)
SCAN_PLAN_SUFFIX = "+scan-plan"
#: appended to a policy argument, lets ``dwa+scan-plan`` drive while the policy stalls (``curlnav.planners.rescue``)
RESCUE_SUFFIX = "+rescue"
#: appended last to a policy or map-less planner, votes its movable labels over the last scans (``curlnav.planners.label_filter``)
TRACK_SUFFIX = "+track"
#: appended last to a policy or map-less planner, gives it laser odometry (``curlnav.planners.scan_match``)
SCAN_MATCH_SUFFIX = "+scan-match"
#: appended to a policy artefact whose metadata names a deploy stack: the network alone, without it
BARE_SUFFIX = "+bare"
_DEPLOY = re.compile(r"(\+global-plan|\+scan-plan)?(\+rescue)?(\+shield)?(\+track)?(\+scan-match)?")
_ORDER = "POLICY[+global-plan|+scan-plan][+rescue][+shield][+track][+scan-match]"
#: the suffixes an agent argument stacks, outermost (last written) first
_STACKED = (SCAN_MATCH_SUFFIX, TRACK_SUFFIX, SHIELD_SUFFIX, RESCUE_SUFFIX, SCAN_PLAN_SUFFIX, GLOBAL_PLAN_SUFFIX)


def _shipped_metadata(folder: str) -> tuple[Path, dict] | None:
    """``(path, contents)`` of the ``metadata.json`` of an artefact ``folder`` (or the file itself);
    None when ``folder`` names a planner (``make_agent`` drives the planner, whatever folder has that
    name), there is no such file, it is unreadable, beyond ``curlnav.files``' caps (size, depth,
    duplicate keys; read no further) or no JSON object: the policy loader, which reads it with the
    same caps, reports those in one line itself."""
    if canonical(folder) is not None:
        return None
    path = Path(folder)
    meta = path if path.name == "metadata.json" else path / "metadata.json"
    if not meta.is_file():
        return None
    try:
        contents = read_json(meta, what="metadata.json")
    except (OSError, FileRefused):
        return None
    return (meta, contents) if isinstance(contents, dict) else None


def deploy_stack(spec: str) -> str:
    """The helpers a policy artefact folder is shipped with: its ``metadata.json``'s ``deploy``
    (suffixes in their order, e.g. ``"+rescue+shield"``), "" when it names none or ``spec`` is no
    artefact folder. A malformed one is refused in one line (``ValueError``)."""
    shipped = _shipped_metadata(spec)
    if shipped is None:
        return ""
    meta, contents = shipped
    deploy = contents.get("deploy", "")
    if not isinstance(deploy, str) or not _DEPLOY.fullmatch(deploy):
        raise ValueError(f"{meta}: deploy must be suffixes in the order {_ORDER[6:]}, "
                         f"got {shown(deploy)}")
    return deploy


def rescue_settings(spec: str):
    """The ``RescueConfig`` a policy artefact's rescue takes: its ``metadata.json``'s
    ``deploy_settings.rescue`` (``{"stall_steps": 10}``; fields not given keep their defaults),
    chosen for that policy on its validation worlds; None (the defaults) when it names none or
    ``spec`` (suffixes allowed) is no artefact folder. Unknown or out-of-range fields are refused
    in one line (``ValueError``). It applies wherever the artefact drives behind ``+rescue``: named
    alone, with the suffix, in ``curlnav policy run`` and in ``curlnav ros2 run``."""
    from curlnav.planners.rescue import RescueConfig

    shipped = _shipped_metadata(spec.split("+", 1)[0])
    if shipped is None:
        return None
    meta, contents = shipped
    settings = contents.get("deploy_settings", {})
    if not isinstance(settings, dict) or not set(settings) <= {"rescue"}:
        raise ValueError(f"{meta}: deploy_settings must be an object with at most the key 'rescue', "
                         f"got {shown(settings)}")
    rescue = settings.get("rescue")
    if rescue is None:
        return None
    fields = set(RescueConfig.__dataclass_fields__)
    if not isinstance(rescue, dict) or not set(rescue) <= fields:
        raise ValueError(f"{meta}: deploy_settings.rescue must be an object of {', '.join(sorted(fields))}, "
                         f"got {shown(rescue)}")
    try:
        return RescueConfig(**rescue)
    except ValueError as exc:
        raise ValueError(f"{meta}: deploy_settings.{exc}") from None


def deploy_notice(spec: str, bare_hint: str) -> str:
    """The line that says an artefact named alone drives with its shipped helpers (``deploy_stack``),
    "" when it ships none or ``spec`` carries suffixes; ``bare_hint`` names how to drop them."""
    stack = deploy_stack(spec) if "+" not in spec else ""
    if not stack:
        return ""
    settings = rescue_settings(spec) if RESCUE_SUFFIX in stack else None
    own = ""
    if settings is not None:
        from curlnav.planners.rescue import RescueConfig

        default = RescueConfig()
        changed = [f"{k} {getattr(settings, k)}" for k in RescueConfig.__dataclass_fields__
                   if getattr(settings, k) != getattr(default, k)]
        own = f"; its rescue: {', '.join(changed)} (deploy_settings)" if changed else ""
    return f"{spec}: driven as its artefact ships it, {spec}{stack} (metadata.json deploy{own}; {bare_hint})"


for _planner in (
    Planner("tare-l", "curlnav.planners.local:TareLocalPlanner", "map-less, after TARE's local planner", True),
    Planner("dwa", "curlnav.planners.local:DynamicWindowPlanner", "map-less dynamic window approach", True),
    Planner("oracle", "curlnav.planners.oracle:StaticMapPlanner", "A* on the true map and pose", False),
):
    register(_planner)


def canonical(name: str) -> str | None:
    """The registered name ``name`` stands for (an alias resolved), or None when it names no planner."""
    name = ALIASES.get(name, name)
    return name if name in PLANNERS else None


def make_planner(name: str, env_config) -> object:
    """The planner ``name`` (or an alias) for an environment of ``env_config``; ``ValueError`` naming
    the planners when there is none of that name."""
    key = canonical(name)
    if key is None:
        raise ValueError(f"no planner named {name!r}; planners: {', '.join(PLANNERS)}")
    return PLANNERS[key].load()(env_config)


def make_agent(spec: str, env_config, load_policy: Callable[[str], object],
               global_plan: bool = False) -> tuple[str, object]:
    """``(label, agent)``: a name in ``PLANNERS`` (or ``ALIASES``) is that planner; anything else is
    a policy ``load_policy`` loads (its label: the path as given). A policy named with the suffix
    ``+global-plan``, or any policy when ``global_plan`` is set, follows waypoints on the oracle's
    A* path (``GlobalPlanAgent``; label ``PATH + global plan``); with ``+scan-plan``, waypoints on
    an A* path on a map of its own scans (``curlnav.planners.scan_map``; not with a global plan);
    with ``+rescue``, ``dwa+scan-plan`` (behind a global plan: pure pursuit of the plan) drives while
    the policy stalls (``curlnav.planners.rescue``);
    with ``+shield``, every command goes through the safety shield (``curlnav.planners.shield``);
    with ``+track``, all of them see movable labels voted over the last scans
    (``curlnav.planners.label_filter``); with ``+scan-match`` last, goal and odometry come from
    laser odometry (``curlnav.planners.scan_match``). Suffixes stack in that order:
    ``PATH+scan-plan+rescue+shield+track+scan-match``.
    An artefact folder named without a suffix drives with the helpers its metadata ships it with
    (``deploy_stack``; label: the path as given); ``PATH+bare`` is the network alone.
    A map-less planner takes the same suffixes (``dwa+scan-plan``: ``move_base``'s pairing)."""
    if canonical(spec) is not None:
        agent = make_planner(spec, env_config)
        return agent.label, agent
    label = spec
    bare = spec.endswith(BARE_SUFFIX)
    if bare:
        spec = spec[:-len(BARE_SUFFIX)]  # the network alone, whatever its artefact deploys it with
        if "+" in spec:
            raise ValueError(f"{label}: +bare is the network alone, without any other suffix")
    elif not any(spec.endswith(s) for s in _STACKED):
        spec += deploy_stack(spec)  # an artefact named alone drives as it is shipped
    plain = spec.split("+", 1)[0]
    planner = canonical(plain) is not None
    if planner:
        if not PLANNERS[canonical(plain)].map_less:
            raise ValueError(f"{label}: {plain} plans on the true map; only map-less planners take suffixes")
        load_policy = lambda name, _load=load_policy: make_planner(name, env_config) \
            if canonical(name) is not None else _load(name)  # noqa: E731
    given = {}
    for suffix in _STACKED:  # peeled from the end, outermost first
        given[suffix] = spec.endswith(suffix)
        if given[suffix]:
            spec = spec[:-len(suffix)]
    scan_match, track, shield, rescue, scan_plan = (given[s] for s in _STACKED[:-1])
    global_plan = global_plan or given[GLOBAL_PLAN_SUFFIX]
    for suffix in (*_STACKED, BARE_SUFFIX):
        if suffix in spec:
            raise ValueError(f"{label}: suffixes stack in the order {_ORDER}, each once")
    if scan_plan and global_plan:
        raise ValueError(f"{label}: +scan-plan and a global plan both set the policy's waypoints; choose one")
    if planner and global_plan:
        raise ValueError(f"{label}: a global plan is for policies; a map-less planner takes +scan-plan, "
                         f"+rescue, +shield, +track and +scan-match")
    agent = load_policy(spec)
    if scan_plan:
        from curlnav.planners.scan_map import ScanMapPlanAgent

        agent = ScanMapPlanAgent(agent, env_config, label=spec)
    elif global_plan:
        from curlnav.planners.global_plan import GlobalPlanAgent

        agent = GlobalPlanAgent(agent, env_config, label=spec)
        label = label if shield or rescue or track or scan_match or bare else agent.label  # wrapped again: as given
        if label != agent.label and GLOBAL_PLAN_SUFFIX not in label:
            label += GLOBAL_PLAN_SUFFIX  # the --global-plan flag: said in the label
    if rescue:
        from curlnav.planners.rescue import RescuedPolicy, global_plan_fallback

        settings = rescue_settings(plain) if not planner else None
        # behind a global plan the fallback tracks the plan (pure pursuit), not a plan on its own scans
        fallback = global_plan_fallback(agent) if global_plan else None
        agent = RescuedPolicy(agent, env_config, settings, fallback=fallback, label=label)
    if shield:
        from curlnav.planners.shield import ShieldedPolicy

        agent = ShieldedPolicy(agent, env_config, label=label, static_map=global_plan)  # the plan's map too
    if track:
        from curlnav.planners.label_filter import LabelFilteredPolicy

        agent = LabelFilteredPolicy(agent, env_config, label=label)
    if scan_match:
        from curlnav.planners.scan_match import ScanMatchedPolicy

        agent = ScanMatchedPolicy(agent, env_config, label=label)
    return label, agent


def _planner_list(map_less_only: bool) -> str:
    old = {}
    for alias, name in ALIASES.items():
        old.setdefault(name, []).append(alias)
    parts = []
    for p in PLANNERS.values():
        if map_less_only and not p.map_less:
            continue
        also = "".join(f"; `{a}` is its old name" for a in old.get(p.name, []))
        parts.append(f"`{p.name}` ({p.about}{also})")
    return ", ".join(parts)


def agents_help(map_less_only: bool = False) -> str:
    """The help of an agent argument: ``curlnav eval``'s (every planner), or with ``map_less_only``
    ``curlnav ros2 run``'s (a policy artefact or a map-less planner)."""
    if map_less_only:
        text = ("policy artefact folder (metadata.json + actor.onnx), or a map-less planner: "
                + _planner_list(True))
    else:
        text = ("policy artefact folder or checkpoint .safetensors (append +global-plan to put it behind "
                "a global plan, or +scan-plan behind a plan on its own scans, then +rescue to let dwa+scan-plan "
                "drive while it stalls, then +shield to check each command against the scan, then +track to vote "
                "its movable labels over the last scans, then +scan-match for laser odometry; map-less planners "
                "take them too; an artefact named alone drives with the helpers its metadata ships, +bare "
                "without), or a classical planner: " + _planner_list(False))
    return text.replace("%", "%%")  # argparse formats help with %


def __getattr__(name: str):
    if name in ("global_plan", "label_filter", "local", "oracle", "rescue", "scan_map", "scan_match", "shield"):
        return import_module(f".{name}", __name__)
    raise AttributeError(f"module 'curlnav.planners' has no attribute {name!r}")
