"""Recovery: ``rescue`` (a fallback drives while the controller stalls) and ``manoeuvre`` (the
plan tracker's way out of a jam, planned on the map)."""

__all__ = ["manoeuvre", "rescue"]
