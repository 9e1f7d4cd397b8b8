"""The bus: Zenoh sessions and key helpers (`transport`), the bus's users and access control
(`security`), and the one service base every service shell builds on (`service`).

Submodules are imported on use: `transport` and `security` sit in the bottom layer, `service` in
the middle one, so this package's face names them without importing them.
"""

__all__ = ["security", "service", "transport"]
