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

CODES = {
    F_NONE: "none", F_HEARTBEAT: "heartbeat_lost", F_EMCY: "emcy", F_FOLLOWING: "following_error",
    F_LIMIT: "setpoint_limit", F_DEADLINE: "deadline_burst", F_SETPOINT: "setpoint_source_dead",
    F_DRIVE: "drive_fault", F_SUPERVISOR: "supervisor_lost", F_BUS: "bus_error",
    F_ENABLE: "enable_failed", F_TEST: "test", F_FEEDBACK: "feedback_stale", F_NMT: "nmt_state",
    F_REMOTE: "remote_lost", F_NOT_FOLLOWING: "target_not_followed", F_SIGNAL: "signal",
}


def fault_code_name(code: int) -> str:
    return CODES.get(code, f"fault_{code}")
