"""The systemd unit: parsed key by key for the hardening the service needs, and its
``systemd-analyze security`` exposure where systemd-analyze is installed."""
from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parent.parent / "systemd" / "hexacnc.service"


def parse_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """{section: {key: [values in order]}} (systemd allows repeated keys)."""
    out: dict[str, dict[str, list[str]]] = {}
    sec = None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line[0] in "#;":
            continue
        if line.startswith("[") and line.endswith("]"):
            sec = out.setdefault(line[1:-1], {})
            continue
        assert sec is not None and "=" in line, f"not a unit line: {raw!r}"
        k, v = line.split("=", 1)
        sec.setdefault(k.strip(), []).append(v.strip())
    return out


@pytest.fixture(scope="module")
def svc():
    return parse_unit(UNIT.read_text())["Service"]


def one(svc, key):
    assert key in svc, f"{key}= missing"
    return svc[key][-1]


def test_type_watchdog_and_stop(svc):
    assert one(svc, "Type") == "notify" and one(svc, "NotifyAccess") == "main"
    assert float(one(svc, "WatchdogSec")) > 0
    assert one(svc, "KillMode") == "mixed"          # SIGTERM to the supervisor: it stops under control
    assert float(one(svc, "TimeoutStopSec")) >= 20   # a controlled stop, disable and joins fit in it
    assert one(svc, "Restart") == "on-failure"
    assert one(svc, "ExecStart").startswith("/opt/hexacnc/bin/hexacnc run --config /etc/hexacnc/")
    assert "--socket" not in one(svc, "ExecStart")   # $RUNTIME_DIRECTORY/hexacnc.sock


def test_resources_and_realtime(svc):
    assert re.fullmatch(r"\d+[KMG]", one(svc, "MemoryMax"))
    assert one(svc, "RuntimeDirectory") == "hexacnc"
    mode = int(one(svc, "RuntimeDirectoryMode"), 8)
    assert not mode & 0o022                           # nobody else can write the socket's directory
    assert int(one(svc, "LimitRTPRIO")) >= 80 and one(svc, "LimitMEMLOCK") == "infinity"
    assert set(one(svc, "CapabilityBoundingSet").split()) == {"CAP_SYS_NICE", "CAP_IPC_LOCK"}
    assert set(one(svc, "AmbientCapabilities").split()) <= {"CAP_SYS_NICE", "CAP_IPC_LOCK"}
    assert one(svc, "RestrictRealtime") == "no"       # SCHED_FIFO must stay possible


def test_sandboxing(svc):
    assert one(svc, "User") == "hexacnc" and one(svc, "Group") == "hexacnc"
    for key in ("NoNewPrivileges", "PrivateTmp", "PrivateDevices", "ProtectKernelTunables", "ProtectKernelModules",
                "ProtectKernelLogs", "ProtectControlGroups", "ProtectClock", "ProtectHostname", "RestrictNamespaces",
                "RestrictSUIDSGID", "LockPersonality", "MemoryDenyWriteExecute"):
        assert one(svc, key) == "yes", key
    assert one(svc, "ProtectSystem") == "strict" and one(svc, "ProtectHome") in ("yes", "read-only", "tmpfs")
    assert one(svc, "RestrictAddressFamilies").split() == ["AF_UNIX", "AF_CAN", "AF_NETLINK"]
    assert one(svc, "IPAddressDeny") == "any"
    filters = svc["SystemCallFilter"]
    assert filters[0] == "@system-service"
    denied = " ".join(f for f in filters[1:] if f.startswith("~")).lstrip("~").split()
    assert "@privileged" in denied and "@resources" not in denied   # sched_setscheduler stays
    assert "@memlock" not in denied                                 # mlockall stays


def _exposure() -> tuple[float | None, str]:
    exe = shutil.which("systemd-analyze")
    if exe is None:
        return None, "systemd-analyze is not installed (apt-get install systemd)"
    r = subprocess.run([exe, "security", "--offline=true", "--no-pager", str(UNIT)],
                       capture_output=True, text=True, timeout=60)
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+)", r.stdout + r.stderr)
    if m is None:
        return None, f"systemd-analyze security --offline not supported here: {(r.stderr or r.stdout)[-300:]}"
    return float(m.group(1)), ""


def test_systemd_analyze_security_exposure_at_most_3():
    exposure, why = _exposure()
    if exposure is None:
        pytest.skip(why)
    print(f"systemd-analyze security --offline=true {UNIT.name}: exposure {exposure}")
    assert exposure <= 3.0
