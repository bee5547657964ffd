"""Run commands inside a private network namespace, for cross-process bus tests over udp_multicast.

The namespace is created with ``unshare -n`` (``unshare -rn`` when not root), then
``ip link set lo up multicast on`` and ``ip route add 224.0.0.0/4 dev lo``: multicast stays on the
namespace's own loopback, nothing reaches the host's network and no other test run interferes.
Inside, ``HEXACNC_NETNS=1`` is set.

Pattern for a pytest test that must run inside (it re-runs itself there)::

    from drivers.testing import netns_or_rerun

    @pytest.mark.netns
    def test_cross_process(request):
        if not netns_or_rerun(request):     # outside: the module ran inside a fresh namespace
            return
        ...                                 # inside the namespace: udp_multicast is private
"""
from __future__ import annotations

import functools
import os
import shutil
import subprocess
import sys
import time
from typing import Sequence

ENV_FLAG = "HEXACNC_NETNS"
_SETUP = ("ip link set lo up multicast on && ip route add 224.0.0.0/4 dev lo && "
          f"export {ENV_FLAG}=1 && exec \"$@\"")
REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def inside_netns() -> bool:
    """True inside a namespace made by this module."""
    return os.environ.get(ENV_FLAG) == "1"


def _unshare_prefix() -> list[str]:
    return ["unshare", "-n"] if os.geteuid() == 0 else ["unshare", "-rn"]


@functools.lru_cache(maxsize=1)
def netns_unavailable_reason() -> str | None:
    """None if a private network namespace with multicast on lo can be made here, else why not."""
    if sys.platform != "linux":
        return "network namespaces need Linux"
    for tool in ("unshare", "ip"):
        if shutil.which(tool) is None:
            return f"'{tool}' is not installed"
    try:
        r = subprocess.run(_unshare_prefix() + ["sh", "-c", _SETUP, "netns", "true"],
                           capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"unshare failed: {exc}"
    if r.returncode != 0:
        return f"unshare -n not permitted: {(r.stderr or r.stdout).strip()[:300]}"
    return None


def netns_command(argv: Sequence[str]) -> list[str]:
    """``argv`` wrapped to run inside a fresh namespace (lo up, multicast routed to lo)."""
    return _unshare_prefix() + ["sh", "-c", _SETUP, "netns"] + list(argv)


def run_in_netns(argv: Sequence[str], *, timeout_s: float = 120.0, env: dict | None = None,
                 cwd: str | None = None) -> subprocess.CompletedProcess:
    """Run ``argv`` in a fresh namespace; stdout and stderr captured (text). Never raises on exit code."""
    e = dict(os.environ if env is None else env)
    e["PYTHONPATH"] = REPO_ROOT + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    try:
        return subprocess.run(netns_command(argv), capture_output=True, text=True, timeout=timeout_s,
                              env=e, cwd=cwd or REPO_ROOT)
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        err = exc.stderr.decode() if isinstance(exc.stderr, bytes) else (exc.stderr or "")
        return subprocess.CompletedProcess(list(argv), -9, out, err + f"\n[timed out after {timeout_s:g} s]")


def run_pytest_in_netns(node_ids: Sequence[str], *, timeout_s: float = 120.0,
                        extra_args: Sequence[str] = ()) -> subprocess.CompletedProcess:
    """Run pytest on ``node_ids`` (e.g. ``request.node.nodeid``) inside a fresh namespace."""
    argv = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *extra_args, *node_ids]
    return run_in_netns(argv, timeout_s=timeout_s)


_MODULE_RUNS: dict[str, tuple[subprocess.CompletedProcess, dict[str, str]]] = {}


def _run_module_in_netns(module_path: str, timeout_s: float):
    """Run a whole test module once inside a fresh namespace; per-test outcomes from ``-rA``."""
    if module_path not in _MODULE_RUNS:
        r = run_pytest_in_netns([module_path], timeout_s=timeout_s, extra_args=["-rA", "--no-header"])
        outcomes: dict[str, str] = {}
        for line in r.stdout.splitlines():
            parts = line.split(" ", 2)
            if len(parts) >= 2 and parts[0] in ("PASSED", "FAILED", "ERROR", "SKIPPED"):
                outcomes[parts[1]] = parts[0]
        _MODULE_RUNS[module_path] = (r, outcomes)
    return _MODULE_RUNS[module_path]


def netns_or_rerun(request, timeout_s: float = 180.0) -> bool:
    """In a pytest test: True when already inside a namespace (go on). Otherwise the test's whole
    module is run once inside a fresh namespace (one pytest start-up for all its tests), this
    test's outcome is looked up, the test fails with the inside output if it failed there, and
    False is returned. Skips cleanly when namespaces are unavailable."""
    import pytest

    if inside_netns():
        return True
    reason = netns_unavailable_reason()
    if reason is not None:
        pytest.skip(f"cross-process bus test needs a private network namespace: {reason}")
    nodeid = request.node.nodeid
    r, outcomes = _run_module_in_netns(nodeid.split("::", 1)[0], timeout_s)
    outcome = outcomes.get(nodeid)
    if outcome == "PASSED":
        return False
    tail = (r.stdout[-8000:] + "\n" + r.stderr[-3000:]).strip()
    if outcome == "SKIPPED":
        pytest.skip(f"skipped inside the namespace:\n{tail}")
    if outcome is None:
        pytest.fail(f"no result for {nodeid} inside the namespace (exit {r.returncode}):\n{tail}")
    pytest.fail(f"inside the network namespace the test {outcome} (exit {r.returncode}):\n{tail}")


def sdo_retry(exchange, attempts: int = 10, pause_s: float = 0.05):
    """``exchange()`` (an idempotent SDO read or write of a test's client), repeated when canopen refuses
    an answer: a test's client is a second SDO client on a drive's one SDO server channel, beside the
    daemon's own (torque sampler at rest), and an answer meant for the daemon can reach it."""
    import canopen
    for attempt in range(attempts):
        try:
            return exchange()
        except canopen.SdoCommunicationError:
            if attempt == attempts - 1:
                raise
            time.sleep(pause_s)


def _read_maps(node) -> None:
    """``rpdo.read()`` and ``tpdo.read()`` of ``node``, repeated on an SDO exchange spoilt by another client."""
    def read():
        node.rpdo.read()
        node.tpdo.read()
    sdo_retry(read)


class PdoDecoder:
    """Independent frame decoder for tests: its own bus objects, canopen ``RemoteNode`` objects built
    from the EDS, the PDO mapping read back from the drives by SDO (``rpdo.read()``/``tpdo.read()``),
    and canopen's own ``PdoMap`` decoding. Records, per strut, every decoded target (0x607A),
    controlword (0x6040), position actual (0x6064) and statusword (0x6041).

    Create it while the drives are configured and NMT operational. The decoder is a second SDO client on
    each drive's one SDO server channel: a daemon's own SDO traffic (the torque sampler at rest) can answer
    the decoder's request, which canopen then refuses; the read of the maps is repeated (it only reads).
    """

    def __init__(self, cfg, eds_path=None):
        import canopen

        from . import EDS_PATH
        from .canbus import open_buses
        from .layout import plan_layout

        self.plan = plan_layout(cfg.bus)
        self.buses = open_buses(cfg.bus)
        self.nets = [canopen.Network(b) for b in self.buses]
        self.nodes = []
        for nd in self.plan.nodes:
            node = canopen.RemoteNode(nd.node_id, canopen.import_od(str(eds_path or EDS_PATH), nd.node_id))
            node.sdo.RESPONSE_TIMEOUT = 1.0
            self.nets[nd.bus].add_node(node)
            self.nodes.append(node)
        import can
        for net in self.nets:
            net.notifier = can.Notifier(net.bus, net.listeners, 0.05)
        n = len(self.nodes)
        self.targets: list[list[int]] = [[] for _ in range(n)]
        self.controlwords: list[list[int]] = [[] for _ in range(n)]
        self.positions: list[list[int]] = [[] for _ in range(n)]
        self.statuswords: list[list[int]] = [[] for _ in range(n)]
        for i, node in enumerate(self.nodes):
            _read_maps(node)
            for m in node.rpdo.map.values():
                if m.enabled:
                    m.add_callback(self._cb(i))
            for m in node.tpdo.map.values():
                if m.enabled:
                    m.add_callback(self._cb(i))

    def _cb(self, i):
        sinks = {0x607A: self.targets[i], 0x6040: self.controlwords[i], 0x6064: self.positions[i],
                 0x6041: self.statuswords[i]}

        def cb(m):
            for var in m.map:
                sink = sinks.get(var.index)
                if sink is not None:
                    sink.append(var.raw)
        return cb

    def close(self) -> None:
        for net in self.nets:
            if net.notifier is not None:
                net.notifier.stop(1.0)
                net.notifier = None
        for b in self.buses:
            b.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
