"""curlnav actor: the one episode loop (`loop.EpisodeLoop`, no network) and its service shell
(`service`: assignments from the scheduler, weights from the learner, batches to the replay).
Submodules are imported on use."""

__all__ = ["loop", "service"]
