"""Driving deploy/netcluster.sh from tests: a cluster under its own name, subnet and port
(so it never meets one a benchmark made), skipped with the script's reason where network
namespaces are not allowed, and everything it made checked gone after `down`."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "deploy" / "netcluster.sh"
NO_NETNS = 3  # the script's exit status when namespaces are not available


class NetCluster:
    def __init__(self, nodes: int, name: str, subnet: str, port: int):
        self.nodes, self.name, self.subnet, self.port = nodes, name, subnet, port
        self.opts = ["--name", name, "--subnet", subnet]
        self.state = Path(f"/tmp/nprt-netcluster-{name}")
        self.address: str | None = None

    def run(self, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        env = {**os.environ, "PYTHON": sys.executable, "NPRT_NETCLUSTER_DIR": str(self.state)}
        return subprocess.run(["bash", str(SCRIPT), *args], env=env, text=True,
                              capture_output=True, check=check)

    def up(self, bandwidth: str = "1gbit") -> str:
        if os.geteuid() != 0:
            pytest.skip("deploy/netcluster.sh needs root (network namespaces, tc)")
        if self.state.exists():  # left by a killed earlier run
            self.down()
        res = self.run("up", str(self.nodes), "--bandwidth", bandwidth, "--port",
                       str(self.port), *self.opts, check=False)
        if res.returncode == NO_NETNS:
            pytest.skip(f"network namespaces are not available: {res.stderr.strip()}")
        assert res.returncode == 0, res.stderr
        self.address = res.stdout.strip().splitlines()[-1]
        return self.address

    def down(self) -> str:
        return self.run("down", *self.opts).stderr

    def node_ip(self, i: int) -> str:
        return f"{self.subnet}.{10 + i}"

    def raylet_pid(self, i: int) -> int:
        return int(self.run("raylet-pid", str(i), *self.opts).stdout.strip())

    def leftovers(self) -> list[str]:
        """Anything of this cluster still on the host: namespaces, links, state, cgroups."""
        left = []
        netns = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
        left += [ln for ln in netns.splitlines() if ln.startswith(f"{self.name}-")]
        links = subprocess.run(["ip", "-o", "link", "show"], capture_output=True,
                               text=True).stdout
        left += [ln.split(":")[1].strip() for ln in links.splitlines()
                 if ln.split(":")[1].strip().startswith(f"{self.name}-")]
        if self.state.exists():
            left.append(str(self.state))
        for cg in (Path("/sys/fs/cgroup/cpu"), Path("/sys/fs/cgroup")):
            if (cg / f"{self.name}-netcluster").exists():
                left.append(str(cg / f"{self.name}-netcluster"))
        for proc in Path("/proc").glob("[0-9]*"):  # Ray processes name their session dir
            try:
                if str(self.state).encode() in (proc / "cmdline").read_bytes():
                    left.append(f"pid {proc.name}")
            except OSError:
                continue
        return left
