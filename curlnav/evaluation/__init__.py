"""Evaluating policies: the one evaluation protocol (`protocol`), side-by-side comparisons and the
unseen-world suite (`compare`), curves (`plots`) and trajectory animations (`animation`). The
planners they compare against live in `curlnav.planners`; the studies that train (the ablation,
the paper's experiment) in `curlnav.run`.

Submodules are imported on use.
"""

__all__ = ["animation", "compare", "plots", "protocol"]
