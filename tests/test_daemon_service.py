"""Service plumbing: sd_notify datagrams, the watchdog petted only while the loop advances,
``hexacnc run --duration`` end to end with READY/WATCHDOG/STOPPING, the systemd unit's keys."""
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from hexacnc.commands.run import Watchdog
from hexacnc.daemon import shm as S
from hexacnc.daemon.sdnotify import Notifier

pytestmark = pytest.mark.e2e


REPO = Path(__file__).resolve().parent.parent


def _listener():
    d = tempfile.mkdtemp(prefix="hxn")
    path = os.path.join(d, "notify")
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(path)
    s.settimeout(0.1)
    return d, path, s


def _drain(s):
    out = []
    while True:
        try:
            out.append(s.recv(4096).decode())
        except socket.timeout:
            return out


def test_notifier_sends_datagrams_and_is_silent_without_systemd():
    d, path, s = _listener()
    n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "3000000"})
    assert n.enabled and n.watchdog_s == 3.0
    assert n.notify("READY=1")
    assert _drain(s) == ["READY=1"]
    n.close()
    quiet = Notifier({})
    assert not quiet.enabled and not quiet.notify("READY=1")
    s.close()


class _FakeDaemon:
    def __init__(self):
        self.sh = S.Shared(create=True)
        self.alive = True


def test_watchdog_pets_only_while_cycles_advance():
    d, path, s = _listener()
    fake = _FakeDaemon()
    try:
        wd = Watchdog(fake, Notifier({"NOTIFY_SOCKET": path}), 0.02)
        fake.sh.h[S.H_LOOP_BEAT_NS] = time.monotonic_ns()
        wd.start()
        t_end = time.monotonic() + 0.3
        while time.monotonic() < t_end:          # the loop makes progress
            fake.sh.h[S.H_CYCLES] += 1
            fake.sh.h[S.H_LOOP_BEAT_NS] = time.monotonic_ns()
            time.sleep(0.005)
        moving = len(_drain(s))
        time.sleep(0.3)                           # the loop hangs: counter frozen
        _drain(s)
        time.sleep(0.3)
        hung = len(_drain(s))
        wd.stop_event.set()
        wd.join(1)
        assert moving >= 5 and hung == 0
    finally:
        fake.sh.close()
        s.close()


@pytest.mark.slow
def test_run_duration_notifies_ready_watchdog_and_exits_zero():
    d, path, s = _listener()
    env = dict(os.environ, NOTIFY_SOCKET=path, WATCHDOG_USEC="600000")
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.Popen([sys.executable, "-m", "hexacnc", "run", "--duration", "2",
                             "--socket", os.path.join(d, "hexacnc.sock")],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    msgs = []
    t_end = time.monotonic() + 60
    while proc.poll() is None and time.monotonic() < t_end:
        msgs += _drain(s)
    msgs += _drain(s)
    out, err = proc.communicate(timeout=10)
    s.close()
    first = [m.split("\n")[0] for m in msgs]
    assert proc.returncode == 0, err[-2000:]
    assert first[0] == "READY=1" and first.count("WATCHDOG=1") >= 3 and first[-1] == "STOPPING=1", first
    # the start-up summary names the machine, the bus load, the privileges and the socket
    for needle in ("machine hexacnc-default-1000", "% of the 500 us period", "hot loop privileges", "socket "):
        assert needle in err, needle
    assert not os.path.exists(os.path.join(d, "hexacnc.sock"))


def test_systemd_unit_has_the_required_keys():
    text = (REPO / "systemd" / "hexacnc.service").read_text()
    for key in ("Type=notify", "Restart=on-failure", "LimitRTPRIO=", "LimitMEMLOCK=", "WatchdogSec=",
                "ExecStart=/opt/hexacnc/bin/hexacnc run --config"):
        assert key in text, key


def test_bus_layout_over_the_limit_is_refused_at_start_with_the_figures():
    import dataclasses

    import pytest

    from hexacnc.config import load_config
    from hexacnc.daemon.core import Daemon
    from hexacnc.errors import BusError

    cfg = load_config(None)
    cfg = cfg.replace(bus=dataclasses.replace(cfg.bus, layout="single", buses=1, feedback_divider=1))
    with pytest.raises(BusError) as e:
        Daemon(cfg)
    msg = str(e.value)
    assert "does not fit" in msg and "us per cycle" in msg and "% of the 500 us period" in msg


def test_supervisor_killed_hot_loop_stops_disables_and_exits():
    import signal

    d = tempfile.mkdtemp(prefix="hxk")
    sock = os.path.join(d, "hexacnc.sock")
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.Popen([sys.executable, "-m", "hexacnc", "run", "--socket", sock], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        t_end = time.monotonic() + 60
        while not os.path.exists(sock) and time.monotonic() < t_end and proc.poll() is None:
            time.sleep(0.05)
        assert os.path.exists(sock)
        kids = [int(p) for p in os.listdir("/proc") if p.isdigit() and _ppid(int(p)) == proc.pid
                and " -m hexacnc.daemon." in _cmdline(int(p))]
        assert len(kids) == 2                        # hot loop + simulated drives (not the planning forkserver)
        kids += [int(p) for p in os.listdir("/proc") if p.isdigit() and _ppid(int(p)) == proc.pid
                 and "multiprocessing.forkserver" in _cmdline(int(p))]
        proc.send_signal(signal.SIGKILL)
        proc.wait(5)
        t_end = time.monotonic() + 10
        while any(_alive(k) for k in kids) and time.monotonic() < t_end:
            time.sleep(0.05)
        assert not any(_alive(k) for k in kids)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)


def _ppid(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return -1


def _cmdline(pid):
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _alive(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False
