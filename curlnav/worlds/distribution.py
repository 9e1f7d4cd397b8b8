"""World distributions: a generator family over a seed range, with parameter ranges, as
curriculum material; and the per-actor draws that turn one into a world per episode.

In a curriculum file a stage's ``worlds`` may hold, beside world files and names::

    - {family: barn-3x3, seeds: [0, 99], params: {fill_pct: [0.10, 0.30]}, every: 4, pool: 4}
    - t-maze-doors:0-99            # the same without parameters: FAMILY:LO-HI

- ``seeds: [LO, HI]`` (inclusive) must stay below the family's held-out seeds
  (``curlnav.worlds.core.heldout``: 100 and above are never trained on).
- ``params``: keyword arguments of the family's generator. ``[lo, hi]`` of two numbers is a
  range (integers if both are, inclusive), any other list a choice, anything else a fixed value.
  A seed's parameters are drawn from the seed alone, so a distribution holds exactly one world
  per seed, the same in every process (and its world can be cached and compared).
- ``every`` (default 1): a fresh world is drawn every ``every`` episodes of this distribution;
  the episodes between are spread uniformly over the last ``pool`` (default 4) fresh worlds,
  whose scenes stay built (``NamoEnv.scene_cache``). ``every: 1`` is a new world per episode.
- ``levels`` (default ``uniform``): which seed a fresh draw takes: ``uniform``, ``difficulty``
  (the paper's ordering: a widening frontier of the easiest seeds) or ``plr`` (prioritized level
  replay by learnability and staleness, fresh levels from that frontier): ``curlnav.worlds.levels``.

A distribution travels as its canonical key (``WorldDistribution.key``), e.g.
``barn-3x3:0-99(fill_pct=0.1~0.3)``: the scheduler assigns it, the actor parses and draws it, and
reports come back under it. ``get_world(key)`` gives the distribution's first world (seed LO): what
checks and evaluations of the stage load.
"""

from __future__ import annotations

import inspect
import math
import re
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from curlnav.worlds.core.heldout import check_training_seed, check_training_world, held_out_from
from curlnav.worlds.core.world import World
from curlnav.worlds.levels import LEVEL_SAMPLERS, LevelSampler

DEFAULT_EVERY = 1  # episodes per fresh world
DEFAULT_POOL = 4  # fresh worlds the episodes between fresh draws are spread over
DEFAULT_CACHE = 16  # built worlds (and scenes) an actor keeps, all distributions together
SPEC_KEYS = ("family", "seeds", "params", "every", "pool", "levels")
_KEY = re.compile(r"^(?P<family>[a-z0-9][a-z0-9-]*):(?P<lo>\d+)-(?P<hi>\d+)(?:\((?P<body>[^()]*)\))?$")


class DistributionError(ValueError):
    """A world distribution is malformed; the message is one line."""


def _show(value: Any, limit: int = 40) -> str:
    """A user's value for an error message, truncated."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


@dataclass(frozen=True)
class ParamRange:
    """One generator parameter: a range ``(lo, hi)`` (integers: inclusive), a choice among
    ``options``, or a fixed ``value``."""

    name: str
    lo: float | None = None
    hi: float | None = None
    options: tuple = ()
    value: Any = None
    integer: bool = False

    @staticmethod
    def from_spec(name: str, raw: Any) -> ParamRange:
        if isinstance(raw, (list, tuple)):
            if len(raw) == 2 and all(_number(v) for v in raw):
                lo, hi = raw
                if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
                    raise DistributionError(f"params.{name} must be [lo, hi] with lo <= hi, got {_show(raw)}")
                integer = all(isinstance(v, int) for v in raw)
                return ParamRange(name, lo, hi, integer=integer)
            if not raw or not all(isinstance(v, (str, int, float, bool)) for v in raw):
                raise DistributionError(f"params.{name}: a choice must list numbers or names, got {_show(raw)}")
            return ParamRange(name, options=tuple(raw))
        if raw is None or not isinstance(raw, (str, int, float, bool)):
            raise DistributionError(f"params.{name} must be a value, [lo, hi] or a list of choices, got {_show(raw)}")
        return ParamRange(name, value=raw)

    def draw(self, u: float) -> Any:
        """The value at ``u`` in [0, 1)."""
        if self.options:
            return self.options[min(int(u * len(self.options)), len(self.options) - 1)]
        if self.lo is None:
            return self.value
        if self.integer:
            return int(self.lo + min(int(u * (self.hi - self.lo + 1)), self.hi - self.lo))
        return round(float(self.lo + u * (self.hi - self.lo)), 4)

    def text(self) -> str:
        if self.options:
            return "|".join(str(v) for v in self.options)
        if self.lo is None:
            return str(self.value)
        if self.integer:
            return f"{int(self.lo)}~{int(self.hi)}"
        return f"{float(self.lo)!r}~{float(self.hi)!r}"  # 1.0, not 1: a float range stays one when parsed


def _generator_params(family: str) -> set[str]:
    from curlnav.worlds.families import FAMILIES

    if family not in FAMILIES:
        raise DistributionError(f"unknown world family {_show(family)}; choose from {', '.join(sorted(FAMILIES))}")
    return {p for p in inspect.signature(FAMILIES[family].load()).parameters if p != "seed"}


@dataclass(frozen=True)
class WorldDistribution:
    """A family over training seeds ``lo..hi`` (inclusive) with parameter ranges. Construction
    validates everything (``DistributionError``, one line), held-out seeds included."""

    family: str
    lo: int
    hi: int
    params: tuple[ParamRange, ...] = ()
    every: int = DEFAULT_EVERY
    pool: int = DEFAULT_POOL
    levels: str = "uniform"  # the level sampler (curlnav.worlds.levels.LEVEL_SAMPLERS)

    def __post_init__(self) -> None:
        known = _generator_params(self.family)
        if not (isinstance(self.lo, int) and isinstance(self.hi, int)) or not 0 <= self.lo <= self.hi:
            raise DistributionError(f"{self.family}: seeds must be [lo, hi], whole numbers with 0 <= lo <= hi, "
                                    f"got {_show([self.lo, self.hi])}")
        first_held_out = held_out_from(self.family)
        if self.hi >= first_held_out:
            raise DistributionError(f"{self.family}: seeds [{self.lo}, {_show(self.hi)}] reach into the held-out "
                                    f"seeds (>= {first_held_out}, kept for unseen-world evaluation); train on "
                                    f"0..{first_held_out - 1}")
        for p in self.params:
            if p.name not in known:
                raise DistributionError(f"{self.family} has no parameter {_show(p.name)}; it takes "
                                        f"{', '.join(sorted(known))}")
        for name in ("every", "pool"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise DistributionError(f"{self.family}: {name} must be a whole number >= 1, got {_show(value)}")
        if self.levels not in LEVEL_SAMPLERS:
            raise DistributionError(f"{self.family}: levels must be one of {', '.join(LEVEL_SAMPLERS)}, "
                                    f"got {_show(self.levels)}")

    # -- the two spellings ---------------------------------------------------------------------
    @staticmethod
    def from_spec(raw: Any) -> WorldDistribution:
        """From a curriculum entry ``{family, seeds: [lo, hi], params, every, pool}``."""
        if not isinstance(raw, dict):
            raise DistributionError(f"a world distribution is a mapping of {', '.join(SPEC_KEYS)}, got {_show(raw)}")
        unknown = sorted(str(k) for k in set(raw) - set(SPEC_KEYS))
        if unknown:
            raise DistributionError(f"unknown keys {_show(unknown)} in a world distribution (allowed: "
                                    f"{', '.join(SPEC_KEYS)})")
        family, seeds = raw.get("family"), raw.get("seeds")
        if not isinstance(family, str):
            raise DistributionError(f"a world distribution needs family: NAME, got {_show(family)}")
        if (not isinstance(seeds, list) or len(seeds) != 2
                or not all(isinstance(s, int) and not isinstance(s, bool) for s in seeds)):
            raise DistributionError(f"{family[:40]}: seeds must be [lo, hi] (whole numbers), got {_show(seeds)}")
        params = raw.get("params") or {}
        if not isinstance(params, dict):
            raise DistributionError(f"{family[:40]}: params must be a mapping, got {_show(params)}")
        ranges = tuple(ParamRange.from_spec(str(k), v) for k, v in sorted(params.items(), key=lambda kv: str(kv[0])))
        return WorldDistribution(family, seeds[0], seeds[1], ranges, raw.get("every", DEFAULT_EVERY),
                                 raw.get("pool", DEFAULT_POOL), raw.get("levels", "uniform"))

    @property
    def key(self) -> str:
        """The canonical name: ``FAMILY:LO-HI`` and, when set, ``(name=value,...)`` with the
        parameters and the draw options that differ from their defaults."""
        parts = [f"{p.name}={p.text()}" for p in self.params]
        if self.every != DEFAULT_EVERY:
            parts.append(f"every={self.every}")
        if self.pool != DEFAULT_POOL:
            parts.append(f"pool={self.pool}")
        if self.levels != "uniform":
            parts.append(f"levels={self.levels}")
        return f"{self.family}:{self.lo}-{self.hi}" + (f"({','.join(parts)})" if parts else "")

    @staticmethod
    def parse(key: str) -> WorldDistribution:
        """The distribution a key names (``DistributionError`` if it names none)."""
        m = _KEY.match(key)
        if not m:
            raise DistributionError(f"{_show(key)} is not a world distribution (FAMILY:LO-HI or "
                                    f"FAMILY:LO-HI(name=lo~hi,...))")
        params, every, pool, levels = [], DEFAULT_EVERY, DEFAULT_POOL, "uniform"
        for item in filter(None, (m.group("body") or "").split(",")):
            name, sep, text = item.partition("=")
            if not sep:
                raise DistributionError(f"{_show(key)}: {_show(item)} is not name=value")
            if name == "levels":
                levels = text
                continue
            if name in ("every", "pool"):
                if not text.isdigit():
                    raise DistributionError(f"{_show(key)}: {name} must be a whole number, got {_show(text)}")
                every, pool = (int(text), pool) if name == "every" else (every, int(text))
                continue
            if "|" in text:
                params.append(ParamRange(name, options=tuple(_scalar(v) for v in text.split("|"))))
            elif "~" in text:
                lo, hi = (_scalar(v) for v in text.split("~", 1))
                params.append(ParamRange.from_spec(name, [lo, hi]))
            else:
                params.append(ParamRange(name, value=_scalar(text)))
        return WorldDistribution(m.group("family"), int(m.group("lo")), int(m.group("hi")), tuple(params), every, pool,
                                 levels)

    # -- worlds ----------------------------------------------------------------------------
    @property
    def seeds(self) -> range:
        return range(self.lo, self.hi + 1)

    def params_of(self, seed: int) -> dict[str, Any]:
        """The generator parameters of seed ``seed``: drawn from the seed alone."""
        u = np.random.default_rng([seed, 28]).random(len(self.params))
        return {p.name: p.draw(float(x)) for p, x in zip(self.params, u)}

    def world(self, seed: int) -> World:
        """The distribution's world of ``seed``; a seed outside ``lo..hi`` or held out is refused."""
        from curlnav.worlds.families import generate

        check_training_seed(self.family, seed)
        if seed not in self.seeds:
            raise DistributionError(f"seed {seed} is outside {self.key}")
        params = self.params_of(seed)
        world = generate(self.family, seed, **params)
        shown = " ".join(f"{k}={v}" for k, v in params.items())
        return world.with_changes(source=f"distribution {self.key}: seed {seed}{' ' + shown if shown else ''}")


def _scalar(text: str) -> Any:
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(text.lower(), text)


def is_distribution(spec: Any) -> bool:
    """Whether a world spec string is a distribution key (``FAMILY:LO-HI...``)."""
    return isinstance(spec, str) and _KEY.match(spec) is not None


@dataclass
class _Draws:
    pool: deque
    episodes: int = 0
    fresh: int = 0


@dataclass
class WorldDraws:
    """One actor's draws: ``resolve(spec)`` turns an assigned distribution key into this
    episode's ``World`` (any other spec is returned as it is). Built worlds are kept in an LRU of
    ``cache`` entries, so that a world drawn again, and every world of a pool, costs nothing."""

    seed: Any = 0  # numpy seed (int or sequence): the experiment's seed and the actor's index
    cache: int = DEFAULT_CACHE
    rng: np.random.Generator = field(init=False)
    _worlds: OrderedDict = field(init=False, default_factory=OrderedDict)  # (key, seed) -> World
    _draws: dict = field(init=False, default_factory=dict)  # key -> _Draws
    _parsed: dict = field(init=False, default_factory=dict)  # key -> WorldDistribution
    _samplers: dict = field(init=False, default_factory=dict)  # key -> LevelSampler (levels other than uniform)
    _last: tuple | None = field(init=False, default=None)  # (key, seed) of the world resolve() gave last
    generated: int = 0  # worlds generated (cache misses)

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def resolve(self, spec: Any) -> Any:
        self._last = None
        if not is_distribution(spec):
            check_training_world(spec)  # FAMILY:SEED assigned for training: never a held-out seed
            return spec
        dist = self._parsed.get(spec)
        if dist is None:
            dist = self._parsed[spec] = WorldDistribution.parse(spec)
        state = self._draws.get(spec)
        if state is None:
            state = self._draws[spec] = _Draws(deque(maxlen=dist.pool))
        if state.episodes % dist.every == 0 or not state.pool:
            if dist.levels == "uniform":
                seed = int(self.rng.integers(dist.lo, dist.hi + 1))
            else:
                sampler = self._samplers.get(spec)
                if sampler is None:
                    sampler = self._samplers[spec] = LevelSampler(dist, dist.levels)
                seed = sampler.draw(self.rng)
            world = self.world(dist, seed)
            state.pool.append((seed, world))
            state.fresh += 1
        else:
            seed, world = state.pool[int(self.rng.integers(len(state.pool)))]
        state.episodes += 1
        self._last = (spec, seed)
        return world

    def record(self, success: bool) -> None:
        """The episode on the world ``resolve`` gave last has ended: its level sampler learns
        the outcome (nothing to do for uniform draws or a world that is no distribution's)."""
        last = self.take_last()
        if last is not None:
            self.record_outcome(*last, success)

    def take_last(self) -> tuple[str, int] | None:
        """``(key, seed)`` of the world ``resolve`` gave last (None for a plain world), once:
        what a loop of several environments keeps per environment for ``record_outcome``."""
        last, self._last = self._last, None
        return last

    def record_outcome(self, key: str, seed: int, success: bool) -> None:
        """An episode on seed ``seed`` of distribution ``key`` ended with ``success``."""
        sampler = self._samplers.get(key)
        if sampler is not None:
            sampler.record(seed, success)

    def levels(self, key: str) -> dict | None:
        """The level sampler's summary for distribution ``key`` (None for uniform draws)."""
        sampler = self._samplers.get(key)
        return None if sampler is None else sampler.summary()

    def fresh_draws(self, key: str) -> int:
        """How many fresh worlds this actor has drawn from distribution ``key``."""
        state = self._draws.get(key)
        return 0 if state is None else state.fresh

    def world(self, dist: WorldDistribution, seed: int) -> World:
        """The world of ``seed``, from the cache or generated (held-out seeds refused)."""
        check_training_seed(dist.family, seed)
        key = (dist.key, seed)
        world = self._worlds.get(key)
        if world is None:
            world = self._worlds[key] = dist.world(seed)
            self.generated += 1
            while len(self._worlds) > self.cache:
                self._worlds.popitem(last=False)
        else:
            self._worlds.move_to_end(key)
        return world
