"""The systemd unit: parsed key by key for the hardening the service needs, and its
``systemd-analyze security`` exposure where systemd-analyze is installed."""
from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.serial        # starts processes or keeps time: runs alone (not beside other tests)

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


def _syscalls(exe: str, group: str, seen: set | None = None) -> set[str]:
    """The system calls of a systemd syscall group, nested groups expanded."""
    seen = set() if seen is None else seen
    if group in seen:
        return set()
    seen.add(group)
    r = subprocess.run([exe, "syscall-filter", "--no-pager", group], capture_output=True, text=True, timeout=60)
    out: set[str] = set()
    for line in r.stdout.splitlines()[1:]:
        w = line.strip()
        if not w or w.startswith("#"):
            continue
        out |= _syscalls(exe, w, seen) if w.startswith("@") else {w}
    return out


#: what the hot loop and the supervisor call to get real time and run (hexacnc.daemon.rt, core)
RT_SYSCALLS = {"mlockall", "sched_setscheduler", "sched_setaffinity", "sched_getaffinity", "clock_nanosleep",
               "socket", "bind", "listen", "accept4", "getsockopt", "execve", "clone", "wait4", "mmap",
               "ftruncate", "openat", "unlinkat"}


def test_the_syscall_filter_keeps_what_real_time_needs(svc):
    exe = shutil.which("systemd-analyze")
    if exe is None:
        pytest.skip("systemd-analyze is not installed (apt-get install systemd)")
    filters = svc["SystemCallFilter"]
    allowed = set().union(*(_syscalls(exe, g) for g in filters[0].split()))
    for f in filters[1:]:
        assert f.startswith("~")
        for g in f[1:].split():
            allowed -= _syscalls(exe, g) if g.startswith("@") else {g}
    missing = RT_SYSCALLS - allowed
    assert not missing, f"the unit's SystemCallFilter blocks {sorted(missing)}"


def test_the_units_capabilities_give_sched_fifo_and_mlockall_to_an_unprivileged_user(svc):
    """As the unit runs it (another user, only its ambient capabilities, no_new_privs) the hot
    loop's privilege calls succeed.  Needs root and setpriv; the seccomp filter is checked above."""
    import os
    import pwd
    if os.geteuid() != 0 or shutil.which("setpriv") is None:
        pytest.skip("needs root and setpriv to start a process as another user with the unit's capabilities")
    try:
        pwd.getpwnam("nobody")
    except KeyError:
        pytest.skip("no user nobody")
    caps = ",".join("+" + c.lower().removeprefix("cap_") for c in one(svc, "AmbientCapabilities").split())
    repo = str(UNIT.parent.parent)
    probe = ("import sys; sys.path.insert(0, sys.argv[1]); from hexacnc.daemon import rt; "
             "ok1, m1 = rt.mlockall(); ok2, m2 = rt.sched_fifo(80); print(m1); print(m2); "
             "sys.exit(0 if ok1 and ok2 else 3)")
    py = next((p for p in ("/usr/bin/python3", "/usr/local/bin/python3") if os.path.exists(p)), None)
    if py is None:
        pytest.skip("no system python3 that user nobody may run")
    cmd = ["setpriv", "--reuid=nobody", "--regid=nogroup", "--clear-groups", f"--inh-caps=-all,{caps}",
           f"--ambient-caps=-all,{caps}", f"--bounding-set=-all,{caps}", "--no-new-privs", py, "-c", probe, repo]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd="/")
    if r.returncode not in (0, 3):
        pytest.skip(f"cannot start a process with these capabilities here: {r.stderr.strip()[-200:]}")
    print(r.stdout.strip())
    assert r.returncode == 0, r.stdout + r.stderr
    assert "memory locked" in r.stdout and "SCHED_FIFO priority 80" in r.stdout
