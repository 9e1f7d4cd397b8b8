"""Controllers besides a trained policy: ``local`` (the map-less ``tare-l`` and ``dwa``, on the same
scan as a policy)."""

__all__ = ["local"]
