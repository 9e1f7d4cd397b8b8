"""curlnav learner: the D4PG core (`d4pg`: state, update, checkpoints), the networks and behaviour
policy (`networks`), policy artefacts (`artefact`), where a run's networks start (`init_from`: a
policy artefact, a run or a checkpoint), the sampled batches' feed from the replay (`feed`) and its
service shell (`service`). Submodules are imported on use."""

__all__ = ["artefact", "d4pg", "feed", "init_from", "networks", "service"]
