"""curlnav actor: the one episode loop (`loop.EpisodeLoop`, no network), the same for K environments
with one batched policy call (`vector`), the batches kept until the replay acknowledges them
(`resend`) and its service shell (`service`: assignments from the scheduler, weights from the
learner, batches to the replay). Submodules are imported on use."""

__all__ = ["loop", "resend", "service", "vector"]
