"""curlnav learner: the D4PG core (`d4pg`: state, update, checkpoints), the networks and behaviour
policy (`networks`), policy artefacts (`artefact`), the sampled batches' feed from the replay
(`feed`) and its service shell (`service`). Submodules are imported on use."""

__all__ = ["artefact", "d4pg", "feed", "networks", "service"]
