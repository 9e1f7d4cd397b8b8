"""Which seed of a world distribution an actor trains on next: the level samplers.

A distribution's ``levels`` option (``{family, seeds, levels: plr}`` or ``levels=plr`` in its key)
picks one; every actor (and the serial trainer, through the same ``EpisodeLoop``) keeps its own
sampler per distribution and feeds it the outcome of every episode on a drawn world.

- ``uniform`` (default): every training seed alike.
- ``difficulty`` (the paper's ordering): the seeds are ranked once by the BARN difficulty of their
  worlds (``curlnav.worlds.difficulty.rank``: ``z(Tortuosity) - z(Distance)`` across the distribution's
  seeds), and fresh worlds come from a *frontier* of the easiest ones. The frontier starts at a
  quarter of the seeds (at least ``pool``) and widens by a tenth of them whenever the last
  ``WIDEN_WINDOW`` episodes on its worlds succeed at least ``WIDEN_AT``.
- ``plr`` (Prioritized Level Replay, Jiang et al. 2021, with the learnability score of
  Rutherford et al. 2024 in place of PLR's value loss, which an off-policy actor does not have):
  with probability ``REPLAY_PROB`` (once ``pool`` levels have been seen) a seen level is replayed,
  drawn by ``(1 - STALENESS) * P_score + STALENESS * P_stale``, where ``P_score`` is rank-based
  on the learnability ``p (1 - p)`` (``p``: the level's moving-average success) with temperature
  ``TEMPERATURE`` and ``P_stale`` grows with the episodes since the level was last drawn; otherwise
  an unseen level from the difficulty frontier (as ``difficulty``). Levels that are always solved
  or never solved fall back; those at the edge of what the policy can do are replayed.

The ranking of a distribution is computed once per process (about 0.2-0.4 s per BARN-3x3 world,
0.03 s per T-Maze or NAMO world) and cached on disk under ``$XDG_CACHE_HOME/curlnav/levels``
(worlds are a function of family, seed and parameters, so the cache never goes stale).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import tempfile
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

log = logging.getLogger("curlnav.levels")

LEVEL_SAMPLERS = ("uniform", "difficulty", "plr")
FRONTIER_START = 0.25  # fraction of the seeds the difficulty frontier starts with
FRONTIER_STEP = 0.10  # fraction of the seeds it widens by
WIDEN_WINDOW = 20  # episodes on the frontier's worlds judged for a widening
WIDEN_AT = 0.5  # success over that window that widens it
REPLAY_PROB = 0.5  # PLR: chance to replay a seen level (once `pool` levels are seen)
STALENESS = 0.3  # PLR: weight of staleness in the replay distribution (rho)
TEMPERATURE = 0.3  # PLR: rank prioritisation temperature (beta)
SUCCESS_EMA = 0.3  # weight of the newest outcome in a level's moving-average success
RANKING_VERSION = 1  # bump when the difficulty measure changes (cache key)


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "curlnav" / "levels"


def difficulty_order(dist) -> list[int]:
    """The distribution's training seeds from easiest to hardest by the paper's difficulty
    (``z(Tor) - z(Dist)`` across these seeds; ties by seed). Cached in memory and on disk."""
    key = dist.key.split("(")[0] + "|" + "|".join(f"{p.name}={p.text()}" for p in dist.params)
    if key in _ORDERS:
        return _ORDERS[key]
    digest = hashlib.sha256(f"{RANKING_VERSION}|{key}".encode()).hexdigest()[:20]
    path = _cache_dir() / f"{dist.family}-{digest}.json"
    order = None
    try:
        saved = json.loads(path.read_text())
        if saved.get("key") == key and sorted(saved["order"]) == list(dist.seeds):
            order = [int(s) for s in saved["order"]]
    except (OSError, ValueError, KeyError, TypeError):
        order = None
    if order is None:
        order = _measure_order(dist)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".")
            with os.fdopen(fd, "w") as f:
                json.dump({"key": key, "order": order}, f)
            os.replace(tmp, path)
        except OSError as exc:  # a read-only home: measured again next time
            log.warning("level ranking of %s not cached (%s)", dist.key, exc)
    _ORDERS[key] = order
    return order


_ORDERS: dict[str, list[int]] = {}


def _measure_order(dist) -> list[int]:
    from curlnav.worlds.difficulty.rank import measure, zscore

    seeds = list(dist.seeds)
    log.info("ranking the %d worlds of %s by difficulty (once; cached)", len(seeds), dist.key)
    metrics = np.array([measure(dist.world(s)).metrics for s in seeds])
    z = zscore(metrics)
    difficulty = z[:, 4] - z[:, 0]  # tortuosity up, distance to obstacles down: harder
    return [s for _, s in sorted(zip(difficulty.tolist(), seeds))]


@dataclass
class LevelSampler:
    """One actor's sampler over one distribution (``mode`` one of ``LEVEL_SAMPLERS``): ``draw``
    the seed of the next fresh world, ``record`` each episode's outcome on a seed."""

    dist: object  # WorldDistribution
    mode: str = "plr"
    order: list[int] = field(default_factory=list)  # seeds, easiest first
    frontier: int = 0  # the easiest `frontier` seeds are open to fresh draws
    success: dict = field(default_factory=dict)  # seed -> moving-average success
    last_drawn: dict = field(default_factory=dict)  # seed -> draw count when last drawn
    draws: int = 0
    widened: int = 0
    window: deque = field(default_factory=lambda: deque(maxlen=WIDEN_WINDOW))

    def __post_init__(self) -> None:
        if self.mode not in LEVEL_SAMPLERS:
            raise ValueError(f"levels must be one of {', '.join(LEVEL_SAMPLERS)}, got {self.mode!r}")
        if not self.order:
            self.order = difficulty_order(self.dist) if self.mode != "uniform" else list(self.dist.seeds)
        n = len(self.order)
        self.frontier = n if self.mode == "uniform" else min(n, max(self.dist.pool, math.ceil(FRONTIER_START * n)))

    def draw(self, rng: np.random.Generator) -> int:
        """The seed of the next fresh world."""
        self.draws += 1
        seen = list(self.success)
        if self.mode == "plr" and len(seen) >= min(self.dist.pool, len(self.order)) and rng.random() < REPLAY_PROB:
            seed = seen[int(rng.choice(len(seen), p=self.replay_distribution(seen)))]
        else:
            open_seeds = self.order[:self.frontier]
            if self.mode == "plr":
                unseen = [s for s in open_seeds if s not in self.success]
                open_seeds = unseen or open_seeds
            seed = open_seeds[int(rng.integers(len(open_seeds)))]
        self.last_drawn[seed] = self.draws
        return seed

    def replay_distribution(self, seen: list[int]) -> np.ndarray:
        """PLR's replay distribution over ``seen``: rank-based learnability mixed with staleness."""
        p = np.array([self.success[s] for s in seen])
        score = p * (1.0 - p)
        ranks = np.empty(len(seen))
        ranks[np.argsort(-score, kind="stable")] = np.arange(1, len(seen) + 1)
        by_score = (1.0 / ranks) ** (1.0 / TEMPERATURE)
        by_score /= by_score.sum()
        stale = np.array([self.draws - self.last_drawn.get(s, 0) for s in seen], dtype=float)
        by_stale = stale / stale.sum() if stale.sum() > 0 else np.full(len(seen), 1.0 / len(seen))
        return (1.0 - STALENESS) * by_score + STALENESS * by_stale

    def record(self, seed: int, success: bool) -> None:
        """An episode on ``seed`` ended (``success``): the level's score, and the frontier."""
        old = self.success.get(seed)
        self.success[seed] = float(success) if old is None else (1 - SUCCESS_EMA) * old + SUCCESS_EMA * float(success)
        if self.mode == "uniform" or seed not in self.order[:self.frontier]:
            return
        self.window.append(bool(success))
        if (len(self.window) == WIDEN_WINDOW and sum(self.window) >= WIDEN_AT * WIDEN_WINDOW
                and self.frontier < len(self.order)):
            self.frontier = min(len(self.order), self.frontier + max(1, math.ceil(FRONTIER_STEP * len(self.order))))
            self.widened += 1
            self.window.clear()
            log.info("%s: difficulty frontier widened to the easiest %d of %d seeds", self.dist.key, self.frontier,
                     len(self.order))

    def summary(self) -> dict:
        """What a status line shows: frontier, levels seen, their mean success."""
        return {"levels": self.mode, "frontier": self.frontier, "seeds": len(self.order), "seen": len(self.success),
                "mean_success": float(np.mean(list(self.success.values()))) if self.success else 0.0}
