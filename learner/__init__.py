"""curlnav learner: the D4PG core (`d4pg`: state, update, checkpoints), the networks and behaviour
policy (`networks`), policy artefacts (`artefact`), its service shell (`service`) and `curlnav bench
learner` (`bench`). Submodules are imported on use."""

__all__ = ["artefact", "bench", "d4pg", "networks", "service"]
