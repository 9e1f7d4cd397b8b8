"""Safety: ``shield`` (each command's arc checked against the scan before it goes out, as Nav2's
collision monitor) and ``push_check`` (when a return labelled movable near the base is believed)."""

__all__ = ["push_check", "shield"]
