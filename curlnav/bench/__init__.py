"""Benchmarks of the distributed service: `curlnav bench transport` (`transport`) and
`curlnav bench faults` (`faults`); of world draws in the episode loop: `curlnav bench draws`
(`draws`). The simulator's, the worlds' and the learner's benches live with their packages
(`curlnav.sim.bench`, `curlnav.worlds.bench`, `curlnav.learner.bench`)."""

__all__ = ["draws", "faults", "transport"]
