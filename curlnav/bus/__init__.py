"""The bus: Zenoh sessions and key helpers (`transport`), the bus's users and access control
(`security`), the actor identity each replica claims (`identity`), how the routers of several
hosts link (`mesh`), the router's audit of what its access control refuses (`audit`), and the one
service base every service shell builds on (`service`); `commands` adds `curlnav bus credentials`.

Submodules are imported on use (importing the package loads no Zenoh): this package's face names
them without importing them.
"""

__all__ = ["audit", "commands", "identity", "mesh", "security", "service", "transport"]
