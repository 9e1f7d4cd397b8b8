"""Held-out seeds: the one place that says which generated worlds no training run may use.

Every family's seeds from ``HELD_OUT_FROM`` (100) upward are held out: nobody trains or tunes on
them (issue 28). Curricula are refused at load when a stage or an ``evaluate`` target names one
(``FAMILY:SEED``, ``FAMILY:LO-HI`` or ``{family, seeds: [LO, HI]}``); the world draws of both
training modes refuse one at draw time (``check_training_seed``), and so does the training
environment for its first world (``check_training_world``: ``curlnav train --world namo-office:300``). The unseen-world suite of
``curlnav eval`` evaluates on these seeds only (``held_out_seeds``); the NAMO figures of the
issue use seed 300.
"""

from __future__ import annotations

HELD_OUT_FROM = 100  # the first held-out seed of every family
MAX_SEED = 2 ** 32 - 1  # numpy's largest seed for one integer



class HeldOutSeedError(ValueError):
    """A training path asked for a held-out seed (or a real suite's map)."""


#: the prefix of the real suite's worlds (``curlnav.worlds.real.real_maps``): held out as a whole
REAL_PREFIX = "real:"


def held_out_from(family: str) -> int:
    """The first held-out seed of ``family``: ``HELD_OUT_FROM`` for every family."""
    return HELD_OUT_FROM


def training_seeds(family: str) -> range:
    """The seeds of ``family`` that training may draw: ``range(0, held_out_from(family))``."""
    return range(0, held_out_from(family))


def held_out_seeds(family: str) -> range:
    """The seeds of ``family`` reserved for evaluation on unseen worlds."""
    return range(held_out_from(family), MAX_SEED + 1)


def is_held_out(family: str, seed: int) -> bool:
    return seed >= held_out_from(family)


def check_training_seed(family: str, seed: int) -> int:
    """``seed`` if training may use it, else ``HeldOutSeedError`` (one line)."""
    if is_held_out(family, seed):
        raise HeldOutSeedError(f"{family} seed {seed} is held out for evaluation (seeds >= {held_out_from(family)}); "
                               f"train on seeds 0..{held_out_from(family) - 1}")
    return seed


def check_training_world(spec) -> None:
    """Refuse a world spec ``FAMILY:SEED`` whose seed is held out, or a real suite's map ``real:NAME``
    (``HeldOutSeedError``); any other spec (a file, a built-in, a ``World``, a distribution's key)
    passes."""
    if not isinstance(spec, str):
        return
    if spec.startswith(REAL_PREFIX):
        raise HeldOutSeedError(f"{spec[:60]} is a map of the real suite (curlnav eval --suite real), kept for "
                               f"evaluation: nobody trains or tunes on it")
    family, sep, seed = spec.rpartition(":")
    if sep and family and seed.isascii() and seed.isdigit():
        check_training_seed(family, int(seed))
