"""Evaluating policies: the one evaluation protocol (`protocol`), the oracle and the global plan
(`baseline`), the map-less classical baselines tare-l and dwa (`local_planners`), side-by-side
comparisons and the unseen-world suite (`compare`), the curriculum ablation (`ablation`), the
paper's experiment report (`experiment`, `experiment_cli`), curves (`plots`) and trajectory
animations (`animation`).

Submodules are imported on use (they span layers).
"""

__all__ = ["ablation", "animation", "baseline", "compare", "experiment", "experiment_cli", "local_planners", "plots",
           "protocol"]
