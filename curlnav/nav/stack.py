"""A navigation stack as configuration: which entry each role runs, with which settings.

``NavStack`` is frozen, validated when made and serialisable (``to_dict``/``from_dict``, YAML with
``to_yaml``/``load_stack``): a controller, and at most one global planner, recovery and safety
entry, and perception entries in their fixed order (``curlnav.nav.registry``). Every entry's
settings are its config dataclasses, each field resolved (a setting not given takes its
default). ``build_stack`` (``curlnav.nav.build``) makes the agent a stack names.

An agent argument is a shorthand parsed into a stack (``parse_agent``): a planner name alone
(``dwa``), a policy artefact folder named alone (the stack its ``metadata.json`` ships), or a
controller with suffixes, one per entry, in the order
``POLICY[+global-plan|+scan-plan][+rescue][+shield][+track][+scan-match]`` (a map-less planner in
POLICY's place too); ``POLICY+bare``
is the network alone. A spelling that means nothing (a role named twice, ``+bare`` after a
planner or with other suffixes, an unknown suffix) is refused in one line naming the valid form.

An artefact's ``metadata.json`` carries its stack as ``"stack"`` (``to_dict`` without the
controller and label: the artefact is the controller); the older ``"deploy"`` string of suffixes
with its ``"deploy_settings"`` still loads.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from curlnav.files import FileRefused, read_json, read_yaml, shown
from curlnav.nav.registry import (
    BARE_SUFFIX,
    ENTRIES,
    GLOBAL_PLAN_SUFFIX,
    PERCEPTION_ORDER,
    POLICY_ENTRY,
    ROLES,
    Entry,
    canonical,
    entry_of_suffix,
    planners,
    suffixes,
)

#: the written order of an agent argument's suffixes, for messages
ORDER = "POLICY[+global-plan|+scan-plan][+rescue][+shield][+track][+scan-match]"
#: at most this many bytes of a stack file
MAX_STACK_BYTES = 256 * 1024


def _check_value(where: str, value: Any, default: Any) -> Any:
    """``value`` for a setting whose default is ``default``: of the same kind (a whole number, a
    number, true/false, text, a list), numbers finite; else ``ValueError`` naming ``where``."""
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ValueError(f"{where} must be true or false, got {shown(value)}")
        return value
    if isinstance(default, int) and not isinstance(default, bool):
        if not isinstance(value, int) or isinstance(value, bool):
            raise ValueError(f"{where} must be a whole number, got {shown(value)}")
        return value
    if isinstance(default, float) or default is None and isinstance(value, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                and not (isinstance(default, float) and math.isinf(default) and math.isinf(value)):
            raise ValueError(f"{where} must be a finite number, got {shown(value)}")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ValueError(f"{where} must be text, got {shown(value)}")
        return value
    if isinstance(default, tuple):
        if not isinstance(value, (list, tuple)) or len(value) != len(default):
            raise ValueError(f"{where} must be a list of {len(default)}, got {shown(value)}")
        return tuple(_check_value(f"{where}[{i}]", v, d) for i, (v, d) in enumerate(zip(value, default, strict=True)))
    if value != default and default is not None:
        raise ValueError(f"{where}: cannot be set (got {shown(value)})")
    return value


def make_config(cls: type, values: Mapping[str, Any], where: str):
    """A config dataclass ``cls`` from ``values`` (fields not given keep their defaults): unknown
    fields, values of the wrong kind and the class's own checks refused in one line naming ``where``."""
    if not isinstance(values, Mapping):
        raise ValueError(f"{where} must be a mapping of settings, got {shown(values)}")
    defaults = cls()
    known = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"{where}: no setting {', '.join(map(repr, unknown))}; settings: {', '.join(sorted(known))}")
    checked = {k: _check_value(f"{where}.{k}", v, getattr(defaults, k)) for k, v in values.items()}
    try:
        return cls(**checked)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: {exc}") from None


def _plain(value: Any) -> Any:
    """A config value as YAML/JSON writes it (tuples as lists)."""
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    return value


@dataclass(frozen=True)
class RoleChoice:
    """One role's entry (``entry``: its name in ``curlnav.nav.registry.ENTRIES[role]``) and its
    settings: section -> config dataclass, every section of the entry present. A policy controller's
    one setting is ``path`` (an artefact folder or checkpoint)."""

    role: str
    entry: str
    settings: tuple[tuple[str, Any], ...] = ()
    path: str = ""

    def __post_init__(self) -> None:
        registered = ENTRIES.get(self.role, {})
        if self.entry not in registered:
            raise ValueError(f"{self.role}: no entry {self.entry!r}; entries: {', '.join(registered)}")
        if (self.entry == POLICY_ENTRY) != bool(self.path):
            raise ValueError(f"{self.role}: a path is the policy entry's one setting"
                             if self.path else "controller: policy needs the path of an artefact or checkpoint")

    @property
    def info(self) -> Entry:
        return ENTRIES[self.role][self.entry]

    def config(self, section: str):
        """The config of ``section``."""
        return dict(self.settings)[section]

    def kwargs(self) -> dict[str, Any]:
        """keyword -> config, as the entry's class takes them."""
        own = dict(self.settings)
        return {keyword: own[section] for section, keyword, _ in self.info.sections}

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"entry": self.entry}
        if self.path:
            out["path"] = self.path
        for section, config in self.settings:
            out[section] = {f.name: _plain(getattr(config, f.name)) for f in dataclasses.fields(config) if f.init}
        return out


def choose(role: str, entry: str, sections: Mapping[str, Mapping[str, Any]] | None = None,
           path: str = "", where: str = "") -> RoleChoice:
    """``role``'s ``entry`` with ``sections`` (section -> field -> value; fields not given keep their
    defaults), each validated; ``where`` prefixes errors (default: the role)."""
    where = where or role
    registered = ENTRIES.get(role)
    if registered is None:
        raise ValueError(f"{where}: no role {role!r}; roles: {', '.join(ROLES)}")
    if not isinstance(entry, str) or entry not in registered:
        raise ValueError(f"{where}: no entry {shown(entry)}; entries: {', '.join(registered)}")
    sections = dict(sections or {})
    info = registered[entry]
    classes = info.config_classes()
    unknown = sorted(set(sections) - set(classes))
    if unknown:
        raise ValueError(f"{where}: {entry} has no settings {', '.join(map(repr, unknown))}; its settings: "
                         f"{', '.join(classes) or 'none'}")
    if (entry == POLICY_ENTRY) != bool(path):
        raise ValueError(f"{where}: a policy needs the path of an artefact or checkpoint (path: FOLDER)"
                         if not path else f"{where}: {entry} takes no path (a policy's setting)")
    settings = tuple((name, make_config(cls, sections.get(name, {}), f"{where}.{name}")) for name, cls in classes.items())
    return RoleChoice(role, entry, settings, path)


@dataclass(frozen=True)
class NavStack:
    """A whole stack: ``controller`` innermost, then the global planner, recovery, safety and the
    perception entries (``curlnav.nav.registry.PERCEPTION_ORDER``) wrapped round it in that order.
    ``label``: the agent's name in results ("" for a planner named alone: its own name)."""

    controller: RoleChoice
    global_planner: RoleChoice | None = None
    recovery: RoleChoice | None = None
    safety: RoleChoice | None = None
    perception: tuple[RoleChoice, ...] = ()
    label: str = ""

    def __post_init__(self) -> None:
        for role in ROLES[:-1]:
            choice = getattr(self, role)
            if choice is not None and (not isinstance(choice, RoleChoice) or choice.role != role):
                raise ValueError(f"{role}: not a {role} entry: {shown(choice)}")
        if self.controller is None:
            raise ValueError("a stack needs a controller")
        names = [c.entry for c in self.perception]
        if any(c.role != "perception" for c in self.perception):
            raise ValueError("perception: only perception entries")
        if len(set(names)) < len(names):
            raise ValueError(f"perception: an entry is named twice: {', '.join(names)}")
        if names != [n for n in PERCEPTION_ORDER if n in names]:
            raise ValueError(f"perception: entries run in the order {', '.join(PERCEPTION_ORDER)}, got {', '.join(names)}")
        wrapped = bool(names) or any(getattr(self, role) is not None for role in ("global_planner", "recovery", "safety"))
        if not self.controller.info.map_less and wrapped:
            raise ValueError(f"controller {self.controller.entry} plans on the true map; only map-less controllers "
                             f"and policies take other roles")

    @property
    def map_less(self) -> bool:
        """Every entry sees only what a robot has (no true map or pose): it runs on a robot."""
        choices = [self.controller, self.global_planner, self.recovery, self.safety, *self.perception]
        return all(c.info.map_less for c in choices if c is not None)

    @property
    def shorthand(self) -> str:
        """The agent argument this stack's entries spell (with default settings), e.g.
        ``policies/x+rescue+shield``; "" when a role's entry has no suffix."""
        head = self.controller.path or self.controller.entry
        parts = [c.info.suffix for c in (self.global_planner, self.recovery, self.safety, *self.perception)
                 if c is not None]
        return "" if any(not p for p in parts) else head + "".join(parts)

    def helpers(self) -> dict[str, Any]:
        """Every role but the controller, as ``metadata.json``'s ``"stack"`` holds them."""
        out: dict[str, Any] = {}
        for role in ("global_planner", "recovery", "safety"):
            choice = getattr(self, role)
            if choice is not None:
                out[role] = choice.to_dict()
        if self.perception:
            out["perception"] = [c.to_dict() for c in self.perception]
        return out

    def to_dict(self) -> dict[str, Any]:
        """The whole stack: ``label``, ``controller`` and every role (null where none)."""
        helpers = self.helpers()
        return {"label": self.label, "controller": self.controller.to_dict(),
                **{role: helpers.get(role) for role in ("global_planner", "recovery", "safety")},
                "perception": helpers.get("perception", [])}

    def to_yaml(self) -> str:
        import yaml

        return yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=False, width=100)

    @staticmethod
    def from_dict(data: Any, where: str = "stack") -> NavStack:
        """A stack from ``to_dict``'s form, every part validated; errors name ``where`` and the key."""
        if not isinstance(data, Mapping):
            raise ValueError(f"{where} must be a mapping of roles, got {shown(data)}")
        keys = {"label", *ROLES}
        unknown = sorted(set(data) - keys)
        if unknown:
            raise ValueError(f"{where}: no key {', '.join(map(repr, unknown))}; keys: label, {', '.join(ROLES)}")
        label = data.get("label") or ""
        if not isinstance(label, str) or len(label) > 200:
            raise ValueError(f"{where}.label must be text of at most 200 characters, got {shown(label)}")
        if data.get("controller") is None:
            raise ValueError(f"{where}.controller is missing: a policy (entry: policy, path: FOLDER) or a planner")
        controller = _choice(data["controller"], "controller", f"{where}.controller")
        helpers = helper_roles(data, where)
        try:
            return NavStack(controller=controller, **helpers, label=label)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None


def _choice(data: Any, role: str, where: str) -> RoleChoice:
    """One role's ``{entry: NAME, SECTION: {...}, ...}`` (a bare name: its defaults)."""
    if isinstance(data, str):
        data = {"entry": data}
    if not isinstance(data, Mapping) or "entry" not in data:
        raise ValueError(f"{where} must be an entry name or a mapping with 'entry', got {shown(data)}")
    sections = {k: v for k, v in data.items() if k not in ("entry", "path")}
    path = data.get("path", "")
    if not isinstance(path, str):
        raise ValueError(f"{where}.path must be text, got {shown(path)}")
    return choose(role, data["entry"], sections, path=path, where=where)


def helper_roles(data: Mapping, where: str) -> dict[str, Any]:
    """The roles but the controller from a stack mapping (``NavStack``'s keyword arguments)."""
    out: dict[str, Any] = {}
    for role in ("global_planner", "recovery", "safety"):
        if data.get(role) is not None:
            out[role] = _choice(data[role], role, f"{where}.{role}")
    perception = data.get("perception") or []
    if not isinstance(perception, list):
        raise ValueError(f"{where}.perception must be a list of entries, got {shown(perception)}")
    out["perception"] = tuple(_choice(p, "perception", f"{where}.perception[{i}]") for i, p in enumerate(perception))
    return out


def load_stack(path: str | Path) -> NavStack:
    """The stack of a YAML file (``curlnav stack show`` writes one; ``curlnav eval --stack FILE``
    reads it); its label defaults to the file's name. Errors name the file, in one line."""
    try:
        data = read_yaml(path, max_bytes=MAX_STACK_BYTES, what="stack file")
    except FileRefused as exc:
        raise ValueError(str(exc)) from None
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the stack file ({exc.strerror or exc})") from None
    stack = NavStack.from_dict(data, where=str(path))
    return stack if stack.label else dataclasses.replace(stack, label=Path(path).stem)


# -- an artefact's shipped stack ----------------------------------------------------------------------------
def shipped_metadata(folder: str) -> tuple[Path, dict] | None:
    """``(path, contents)`` of the ``metadata.json`` of an artefact ``folder`` (or the file itself);
    None when ``folder`` names a planner (a planner's name is the planner, whatever folder has that
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


_DEPLOY_FORM = "[+global-plan|+scan-plan][+rescue][+shield][+track][+scan-match]"


def _deploy_suffixes(deploy: str) -> list[str] | None:
    """The suffixes of a ``deploy`` string in their written order, None when it is not one."""
    import re

    if not re.fullmatch(r"(\+global-plan|\+scan-plan)?(\+rescue)?(\+shield)?(\+track)?(\+scan-match)?", deploy):
        return None
    return ["+" + s for s in deploy.split("+")[1:]]


def shipped_helpers(folder: str) -> dict[str, Any] | None:
    """The roles a policy artefact's ``metadata.json`` ships round its network: its ``"stack"``
    (validated), else the ``"deploy"`` suffixes with ``"deploy_settings"``; as ``NavStack``'s
    keyword arguments (without the controller); None when it ships none or ``folder`` is no
    artefact. A malformed one is refused in one line (``ValueError``)."""
    shipped = shipped_metadata(folder)
    if shipped is None:
        return None
    meta, contents = shipped
    deploy = contents.get("deploy", "")
    names = _deploy_suffixes(deploy) if isinstance(deploy, str) else None
    if names is None:
        raise ValueError(f"{meta}: deploy must be suffixes in the order {_DEPLOY_FORM}, got {shown(deploy)}")
    if "stack" in contents:
        stack = contents["stack"]
        if not isinstance(stack, Mapping) or "controller" in stack or "label" in stack:
            raise ValueError(f"{meta}: stack must be a mapping of the roles round the network "
                             f"({', '.join(ROLES[1:])}), got {shown(stack)}")
        helpers = helper_roles(stack, f"{meta}: stack")
        try:
            whole = NavStack(controller=RoleChoice("controller", POLICY_ENTRY, path=folder), **helpers)
        except ValueError as exc:
            raise ValueError(f"{meta}: stack: {exc}") from None
        if "deploy" in contents and whole.shorthand != folder + deploy:
            raise ValueError(f"{meta}: stack and the older deploy {shown(deploy)} name different helpers; "
                             f"keep stack alone")
        return helpers
    settings = contents.get("deploy_settings", {})
    if not isinstance(settings, dict) or not set(settings) <= {"rescue"}:
        raise ValueError(f"{meta}: deploy_settings must be an object with at most the key 'rescue', "
                         f"got {shown(settings)}")
    rescue = settings.get("rescue") or {}
    if not isinstance(rescue, dict):
        raise ValueError(f"{meta}: deploy_settings.rescue must be an object, got {shown(rescue)}")
    if not names:
        return None
    out: dict[str, Any] = {"perception": ()}
    for suffix in names:
        entry = entry_of_suffix(suffix)
        sections = {"rescue": rescue} if entry.name == "rescue" else {}
        choice = choose(entry.role, entry.name, sections, where=f"{meta}: deploy_settings")
        if entry.role == "perception":
            out["perception"] += (choice,)
        else:
            out[entry.role] = choice
    return out


def shipped_rescue(folder: str) -> dict[str, Any]:
    """The rescue settings an artefact ships (``{}`` when none): they apply wherever it drives
    behind a rescue, named alone or with ``+rescue``."""
    helpers = shipped_helpers(folder) or {}
    recovery = helpers.get("recovery")
    if recovery is None or recovery.entry != "rescue":
        return {}
    return recovery.to_dict()["rescue"]


# -- agent arguments ----------------------------------------------------------------------------------------
def agent_form() -> str:
    """How an agent argument is written, for messages."""
    return (f"an agent is a planner ({', '.join(planners())}) or a policy artefact folder or checkpoint, "
            f"optionally followed by suffixes in the order {ORDER} (or POLICY+bare)")


def parse_agent(spec: str, global_plan: bool = False) -> NavStack:
    """The stack an agent argument names (module docstring); ``global_plan``: every policy goes
    behind A* on the true map (``--global-plan``). Refused in one line (``ValueError``) when it means
    nothing."""
    if not isinstance(spec, str) or not spec:
        raise ValueError(f"an agent must be named; {agent_form()}")
    planner = canonical(spec)
    if planner is not None:  # a planner alone: --global-plan is for policies
        return NavStack(controller=choose("controller", planner), label=planner)
    head, *rest = spec.split("+")
    given = ["+" + r for r in rest]
    known = suffixes()
    for suffix in given:
        if suffix not in known:
            raise ValueError(f"{spec}: unknown suffix {shown(suffix)}; suffixes: {', '.join(known)}, "
                             f"written in the order {ORDER}")
    for suffix in set(given):
        if given.count(suffix) > 1:
            raise ValueError(f"{spec}: {suffix} is named {given.count(suffix)} times; each suffix once, "
                             f"in the order {ORDER}")
    if GLOBAL_PLAN_SUFFIX in given and "+scan-plan" in given:
        raise ValueError(f"{spec}: +scan-plan and a global plan both set the policy's waypoints; choose one")
    planner = canonical(head)
    if BARE_SUFFIX in given:
        if planner is not None:
            raise ValueError(f"{spec}: +bare drops the helpers a policy artefact ships with; {head} is a planner: "
                             f"name it alone ({head})")
        if given != [BARE_SUFFIX]:
            others = "".join(s for s in given if s != BARE_SUFFIX)
            raise ValueError(f"{spec}: +bare is the network alone and takes no other suffix; name the helpers "
                             f"you want instead ({head}{others})")
    elif given != [s for s in known if s in given]:
        raise ValueError(f"{spec}: suffixes stack in the order {ORDER}, each once")
    if planner is not None and not planners()[planner].map_less:
        raise ValueError(f"{spec}: {head} plans on the true map; only map-less planners take suffixes")
    label = spec
    bare = given == [BARE_SUFFIX]
    helpers: dict[str, Any] = {"perception": ()}
    if not given and planner is None:  # an artefact named alone drives as it is shipped
        helpers = shipped_helpers(head) or helpers
    elif not bare:
        rescue = shipped_rescue(head) if planner is None else {}
        for suffix in given:
            entry = entry_of_suffix(suffix)
            choice = choose(entry.role, entry.name, {"rescue": rescue} if entry.name == "rescue" else {})
            if entry.role == "perception":
                helpers["perception"] += (choice,)
            else:
                helpers[entry.role] = choice
    planned = helpers.get("global_planner")
    if global_plan and planner is None:
        if planned is not None and planned.entry != "true-map":
            raise ValueError(f"{spec}: +scan-plan and a global plan both set the policy's waypoints; choose one")
        if planned is None:
            helpers["global_planner"] = planned = choose("global_planner", "true-map")
    if planner is not None and planned is not None and planned.entry == "true-map":
        raise ValueError(f"{spec}: a global plan is for policies; a map-less planner takes +scan-plan, "
                         f"+rescue, +shield, +track and +scan-match")
    controller = choose("controller", planner) if planner else choose("controller", POLICY_ENTRY, path=head)
    if planned is not None and planned.entry == "true-map":
        wrapped = bare or bool(helpers["perception"]) or any(helpers.get(r) is not None for r in ("recovery", "safety"))
        if not wrapped:
            label = f"{head} + global plan"  # the plan agent's own label
        elif GLOBAL_PLAN_SUFFIX not in label:
            label += GLOBAL_PLAN_SUFFIX  # the --global-plan flag: said in the label
    return NavStack(controller=controller, **helpers, label=label)
