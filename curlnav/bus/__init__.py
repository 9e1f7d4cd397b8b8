"""The bus: Zenoh sessions and key helpers (`transport`), the bus's users and access control
(`security`), the actor identity each replica claims (`identity`), how the routers of several
hosts link (`mesh`), and the one service base every service shell builds on (`service`).

Submodules are imported on use: `transport`, `security`, `identity` and `mesh` sit in the bottom
layer, `service` in the middle one, so this package's face names them without importing them.
"""

__all__ = ["identity", "mesh", "security", "service", "transport"]
