"""Running training: the `train` command (`train`), the serial trainer (`serial`), the services as
supervised local processes (`launch`, `supervise`), run records (`record`: metrics.csv, eval.csv,
TensorBoard, summary.json), the evaluator beside training (`evaluator`), `curlnav status`
(`status`) and `curlnav pull` (`pull`).

Submodules are imported on use (they span layers: `record` is at the bottom, the rest on top).
"""

__all__ = ["evaluator", "launch", "pull", "record", "serial", "status", "supervise", "train"]
