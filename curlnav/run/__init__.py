"""Running training: the `train` command (`train`), the serial trainer (`serial`), the services as
supervised local processes (`launch`, `supervise`), run records (`record`: metrics.csv, eval.csv,
TensorBoard, summary.json), the evaluator beside training (`evaluator`), `curlnav status`
(`status`), `curlnav pull` (`pull`), and the studies that train: the curriculum ablation
(`ablation`), the paper's experiment report (`experiment`) and the experiment options every
training command shares (`options`); `commands` adds `train`, `config`, `serve`, `pull`, `status`,
`ablation` and `experiment` to the command line.

Submodules are imported on use.
"""

__all__ = ["ablation", "commands", "evaluator", "experiment", "launch", "options", "pull", "record", "serial", "status",
           "supervise", "train"]
