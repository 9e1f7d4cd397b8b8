"""Evaluating policies: the one evaluation protocol (`protocol`), the classical baselines
(`baseline`), side-by-side comparisons (`compare`), the curriculum ablation (`ablation`), the
paper's experiment report (`experiment`, `experiment_cli`), curves (`plots`) and trajectory
animations (`animation`).

Submodules are imported on use (they span layers).
"""

__all__ = ["ablation", "animation", "baseline", "compare", "experiment", "experiment_cli", "plots", "protocol"]
