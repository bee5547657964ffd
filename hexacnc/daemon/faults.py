"""Fault codes of the hot loop (values in the status block) and their texts (slow path)."""
from __future__ import annotations

F_NONE = 0
F_HEARTBEAT = 1         #: strut = node index, arg = ms since the last heartbeat
F_EMCY = 2              #: strut = node index, arg = EMCY error code
F_FOLLOWING = 3         #: strut, arg = following error in um
F_LIMIT = 4             #: arg = CycleTransform code, strut = fail index + 1
F_DEADLINE = 5          #: arg = overruns in a row
F_SETPOINT = 6          #: arg = 1: ring ran empty while moving, 2: no setpoint within the timeout
F_DRIVE = 7             #: strut = node index, arg = statusword (drive left Operation Enabled / fault bit)
F_SUPERVISOR = 8        #: arg = ms since the supervisor's last sign of life
F_BUS = 9               #: arg = errno-like code of the failed send
F_ENABLE = 10           #: drives did not reach Operation Enabled; strut = node, arg = statusword
F_TEST = 11             #: injected by a test command
F_FEEDBACK = 12         #: strut = node index, arg = ms since its last fresh position sample (stale feedback)
F_NMT = 13              #: strut = node index, arg = NMT state from its heartbeat (0: boot-up, the drive was reset)
F_REMOTE = 14           #: strut = node index, arg = statusword (bit 9 "remote" lost: not under bus control)
F_NOT_FOLLOWING = 15    #: strut = node index, arg = statusword (CSP bit 12 "follows command value" cleared)
F_SIGNAL = 16           #: arg = signal number (a signal ended the hot loop: controlled stop, not a fault)
F_HOMING = 18           #: strut (0: all), arg = hexacnc.daemon.homeloop error code (< 0)

CODES = {
    F_NONE: "none", F_HEARTBEAT: "heartbeat_lost", F_EMCY: "emcy", F_FOLLOWING: "following_error",
    F_LIMIT: "setpoint_limit", F_DEADLINE: "deadline_burst", F_SETPOINT: "setpoint_source_dead",
    F_DRIVE: "drive_fault", F_SUPERVISOR: "supervisor_lost", F_BUS: "bus_error",
    F_ENABLE: "enable_failed", F_TEST: "test", F_FEEDBACK: "feedback_stale", F_NMT: "nmt_state",
    F_REMOTE: "remote_lost", F_NOT_FOLLOWING: "target_not_followed", F_SIGNAL: "signal",
    F_HOMING: "homing_failed",
}


def fault_code_name(code: int) -> str:
    return CODES.get(code, f"fault_{code}")


def fault_message(code: int, strut: int, arg: int, emcy_text: str = "", detail: str = "") -> str:
    """Human-readable cause of a fault (slow path)."""
    name = fault_code_name(code)
    if code == F_HEARTBEAT:
        return (f"lost heartbeat of drive {strut}" + (f" ({arg} ms since the last one)" if arg >= 0
                                                       else " (none received)"))
    if code == F_EMCY:
        return f"EMCY from drive {strut}: 0x{arg & 0xFFFF:04X}" + (f" {emcy_text}" if emcy_text else "")
    if code == F_FOLLOWING:
        return f"following error of strut {strut}: {arg / 1000.0:.3f} mm over the limit"
    if code == F_LIMIT:
        return f"setpoint outside limits: {detail}" if detail else f"setpoint outside limits (code {arg})"
    if code == F_DEADLINE:
        return f"missed-deadline burst: {arg} cycles in a row over the period"
    if code == F_SETPOINT:
        return ("dead setpoint source: setpoint ring ran empty while moving" if arg == 1
                else "dead setpoint source: no setpoint within [cycle] setpoint_timeout_s")
    if code == F_DRIVE:
        return f"drive {strut} left Operation Enabled (statusword 0x{arg & 0xFFFF:04X})"
    if code == F_SUPERVISOR:
        return "supervisor process gone" + (f" (last sign of life {arg} ms before)" if arg >= 0 else "")
    if code == F_FEEDBACK:
        return f"stale feedback from drive {strut}: no position sample for {arg} ms"
    if code == F_NMT:
        return (f"drive {strut} was reset (boot-up message)" if arg == 0
                else f"drive {strut} left NMT Operational (heartbeat state {arg})")
    if code == F_REMOTE:
        return f"drive {strut} lost remote (statusword bit 9 clear: 0x{arg & 0xFFFF:04X})"
    if code == F_NOT_FOLLOWING:
        return f"drive {strut} does not follow its target (statusword bit 12 clear: 0x{arg & 0xFFFF:04X})"
    if code == F_HOMING:
        from .homecodes import ERROR_TEXT
        return f"homing failed{f' on strut {strut}' if strut else ''}: {ERROR_TEXT.get(arg, arg)}"
    if code == F_SIGNAL:
        import signal
        try:
            name = signal.Signals(arg).name
        except ValueError:
            name = f"signal {arg}"
        return f"stopped by {name}"
    if code == F_BUS:
        return "bus send failed"
    if code == F_ENABLE:
        if arg == -2:
            return f"drive {strut} reports a position outside the strut length range: not enabled"
        if arg == -1:
            return f"no position feedback from drive {strut}: not enabled"
        if arg >> 16 and arg & 0x4F == 0x08:
            return (f"drive {strut} did not reach Operation Enabled: still in Fault (statusword 0x{arg & 0xFFFF:04X}) "
                    f"after {arg >> 16} fault reset edge(s) (controlword bit 7): the fault persists, see the drive's "
                    "EMCY / error code 0x603F")
        return f"drive {strut} did not reach Operation Enabled (statusword 0x{arg & 0xFFFF:04X})"
    if code == F_TEST:
        return "test fault"
    return name
