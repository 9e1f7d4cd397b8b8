"""The worlds library, below the simulator. At its top: the registry of world families
(`families`), distributions of worlds (`distribution`), curriculum levels (`levels`), the
resolver of world specs and the built-in worlds (`builtin`) and the `curlnav worlds` commands
(`commands`). Below them, in sub-packages, bottom first: the world model, its files, pairs,
held-out seeds and picture (`core`); the BARN difficulty metrics and the ranking (`difficulty`);
the generated families (`procedural`); Gazebo SDF import and real buildings' maps (`real`); the
BARN Challenge's worlds (`barn_challenge`). Each imports only those before it; the vendored
data stays in `data/`.

The modules that moved into the sub-packages keep their old names here:
`from curlnav.worlds import barn` is `curlnav.worlds.barn_challenge.barn`. Submodules are
imported on use."""

__all__ = ["barn", "barn_challenge", "barn_course", "builtin", "commands", "core", "degrade", "difficulty", "distribution",
           "families", "generators", "heldout", "levels", "metrics", "namo", "pairs", "picture", "procedural", "rank", "real",
           "real_maps", "scatter", "sdf", "slam_like", "tmaze", "world"]


def __getattr__(name: str):
    """The modules that moved into sub-packages, by their old names, imported on first use:
    ``from curlnav.worlds import barn`` is ``curlnav.worlds.barn_challenge.barn``."""
    moved_into = {  # module -> the sub-package it lives in
        "barn": "barn_challenge",
        "barn_course": "barn_challenge",
        "degrade": "procedural",
        "generators": "procedural",
        "heldout": "core",
        "metrics": "difficulty",
        "namo": "procedural",
        "pairs": "core",
        "picture": "core",
        "rank": "difficulty",
        "real_maps": "real",
        "scatter": "procedural",
        "sdf": "real",
        "slam_like": "procedural",
        "tmaze": "procedural",
        "world": "core",
    }
    if name in moved_into:
        import importlib

        module = importlib.import_module(f"{__name__}.{moved_into[name]}.{name}")
        globals()[name] = module
        return module
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
