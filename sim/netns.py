"""Network namespaces as hosts, for the multi-host tests and benchmarks
(root and ``ip netns``; docs/hosts.md).

``Namespaces(count)``: a hub namespace with a bridge, and ``count``
namespaces joined to it by a veth pair each, with the address
10.<octet>.<net>.<j + 1>/24 (``net`` from this process's pid, so that two
runs at once do not collide). ``create`` raises ``OSError`` naming the
``ip`` step that failed; ``delete`` removes them all (also as a context
manager).
"""
from __future__ import annotations

import os
import subprocess


def _ip(*args) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)


class Namespaces:
    def __init__(self, count: int, prefix: str = "dkm", octet: int = 213):
        tag = f"{prefix}{os.getpid() % 100000}"
        self.hub = f"{tag}h"
        self.names = [f"{tag}n{j}" for j in range(count)]
        self.net = os.getpid() % 200 + 20
        self.addrs = [f"10.{octet}.{self.net}.{j + 1}" for j in range(count)]
        self.tag = tag

    def create(self) -> None:
        steps = [("netns", "add", self.hub),
                 ("netns", "exec", self.hub, "ip", "link", "add", "br0", "type", "bridge"),
                 ("netns", "exec", self.hub, "ip", "link", "set", "br0", "up")]
        for j, (ns, addr) in enumerate(zip(self.names, self.addrs)):
            a, b = f"{self.tag}a{j}", f"{self.tag}b{j}"
            steps += [("netns", "add", ns),
                      ("link", "add", a, "netns", ns, "type", "veth", "peer", "name", b, "netns", self.hub),
                      ("netns", "exec", self.hub, "ip", "link", "set", b, "master", "br0", "up"),
                      ("netns", "exec", ns, "ip", "addr", "add", f"{addr}/24", "dev", a),
                      ("netns", "exec", ns, "ip", "link", "set", a, "up"),
                      ("netns", "exec", ns, "ip", "link", "set", "lo", "up")]
        for s in steps:
            r = _ip(*s)
            if r.returncode != 0:
                raise OSError(f"ip {' '.join(s)}: {r.stderr.strip()}")

    def delete(self) -> None:
        for ns in (*self.names, self.hub):
            _ip("netns", "del", ns)

    def __enter__(self):
        try:
            self.create()
        except OSError:
            self.delete()
            raise
        return self

    def __exit__(self, *exc):
        self.delete()
