"""Evaluating policies: the one evaluation protocol (`protocol`), side-by-side comparisons and the
unseen-world suite (`compare`), their trials in worker processes (`parallel`), curves (`plots`),
trajectory animations (`animation`) and the
commands `eval`, `policy run` and `rollout` (`commands`). The
planners they compare against live in `curlnav.nav`; the studies that train (the ablation,
the paper's experiment) in `curlnav.run`.

Submodules are imported on use.
"""

__all__ = ["animation", "barn", "commands", "compare", "parallel", "plots", "protocol"]
