"""Hosts on one Linux machine: a network namespace per host, each joined to one bridge by a veth
pair (root only). ``curlnav bench hosts`` and its tests run a router and services per namespace;
``cut`` and ``heal`` take a host's link down and up (a partition; no netem needed), ``netem`` adds
latency and loss where the kernel has it.

    root namespace:  bridge cn<tag>br (<subnet>.254) -- cn<tag>v<i> ==veth== eth0 (<subnet>.<i+1>)  in cn<tag>h<i>
"""

from __future__ import annotations

import os
import shutil
import subprocess


class NetnsUnavailable(RuntimeError):
    """No root, no ``ip``, or the kernel refuses namespaces, veth pairs or bridges here."""


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    result = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    if check and result.returncode != 0:
        raise NetnsUnavailable(f"ip {' '.join(args)}: {result.stderr.strip() or result.returncode}")
    return result


def unavailable() -> str | None:
    """Why namespaces cannot be made here (for a skip reason), or None."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "no `ip` (iproute2)"
    probe = f"cnprobe{os.getpid() % 100000}"
    result = _ip("netns", "add", probe, check=False)
    if result.returncode != 0:
        return f"`ip netns add` refused: {result.stderr.strip()}"
    try:
        # namespaces alone are not enough: the hosts need a bridge and veth pairs too
        for args, what in ((("link", "add", f"{probe}b", "type", "bridge"), "a bridge"),
                           (("link", "add", f"{probe}v", "type", "veth", "peer", "name", f"{probe}p"),
                            "a veth pair")):
            made = _ip(*args, check=False)
            if made.returncode != 0:
                return f"`ip link add` of {what} refused: {made.stderr.strip()}"
    finally:
        _ip("link", "del", f"{probe}b", check=False)
        _ip("link", "del", f"{probe}v", check=False)
        _ip("netns", "del", probe, check=False)
    return None


class Hosts:
    """``count`` namespaces on one bridge. ``tag`` keeps names unique (at most 5 characters:
    interface names have 15); the subnet is drawn from the tag."""

    def __init__(self, count: int, tag: str | None = None) -> None:
        self.count = count
        self.tag = tag or f"{os.getpid() % 100000}"
        n = int.from_bytes(self.tag.encode()[-4:], "big")
        self.subnet = f"10.{200 + n % 50}.{(n // 50) % 250}"
        self.bridge = f"cn{self.tag}br"
        self.made: list[str] = []  # what to take down, in reverse

    def ns(self, i: int) -> str:
        return f"cn{self.tag}h{i}"

    def address(self, i: int) -> str:
        return f"{self.subnet}.{i + 1}"

    def link(self, i: int) -> str:
        """Host ``i``'s veth end on the bridge: down is a partition."""
        return f"cn{self.tag}v{i}"

    def exec(self, i: int) -> list[str]:
        """The command prefix that runs a program in host ``i``."""
        return ["ip", "netns", "exec", self.ns(i)]

    def setup(self) -> Hosts:
        try:
            _ip("link", "add", self.bridge, "type", "bridge")
            self.made.append(f"link:{self.bridge}")
            # a Docker engine sets iptables' FORWARD policy to DROP, which also drops bridged traffic
            # between the namespaces: let this bridge's own traffic through (best effort, no iptables: fine)
            iptables = shutil.which("iptables")
            if iptables and subprocess.run([iptables, *self._forward("-I")], capture_output=True, timeout=30,
                                           check=False).returncode == 0:
                self.made.append(f"iptables:{self.bridge}")  # taken out again at teardown
            _ip("addr", "add", f"{self.subnet}.254/24", "dev", self.bridge)
            _ip("link", "set", self.bridge, "up")
            for i in range(self.count):
                _ip("netns", "add", self.ns(i))
                self.made.append(f"netns:{self.ns(i)}")
                peer = f"cn{self.tag}p{i}"
                _ip("link", "add", self.link(i), "type", "veth", "peer", "name", peer)
                self.made.append(f"link:{self.link(i)}")
                _ip("link", "set", peer, "netns", self.ns(i))
                _ip("link", "set", self.link(i), "master", self.bridge)
                _ip("link", "set", self.link(i), "up")
                inside = ["-n", self.ns(i)]
                _ip(*inside, "link", "set", peer, "name", "eth0")
                _ip(*inside, "addr", "add", f"{self.address(i)}/24", "dev", "eth0")
                _ip(*inside, "link", "set", "eth0", "up")
                _ip(*inside, "link", "set", "lo", "up")
        except BaseException:
            self.teardown()
            raise
        return self

    def _forward(self, action: str) -> list[str]:
        return [action, "FORWARD", "-i", self.bridge, "-o", self.bridge, "-j", "ACCEPT"]

    def cut(self, i: int) -> None:
        """Partition host ``i``: its link down (its processes keep running, nothing reaches them)."""
        _ip("link", "set", self.link(i), "down")

    def heal(self, i: int) -> None:
        _ip("link", "set", self.link(i), "up")

    def netem(self, i: int, spec: str) -> str | None:
        """Latency and loss on host ``i``'s link (``tc qdisc ... netem <spec>``, e.g. "delay 20ms
        loss 1%"); returns why not where the kernel has no netem."""
        result = subprocess.run(["tc", "qdisc", "replace", "dev", self.link(i), "root", "netem", *spec.split()],
                                capture_output=True, text=True, timeout=30)
        return None if result.returncode == 0 else (result.stderr.strip() or "tc failed")

    def teardown(self) -> None:
        """Remove every namespace, link and forwarding rule made (a namespace takes its veth end with it)."""
        for item in reversed(self.made):
            kind, name = item.split(":", 1)
            if kind == "netns":
                _ip("netns", "del", name, check=False)
            elif kind == "iptables":
                subprocess.run([shutil.which("iptables") or "iptables", *self._forward("-D")], capture_output=True,
                               timeout=30, check=False)
            else:
                _ip("link", "del", name, check=False)
        self.made = []

    def __enter__(self) -> Hosts:
        return self.setup()

    def __exit__(self, *exc) -> None:
        self.teardown()
