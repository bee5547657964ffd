"""CiA 402 drive state machine as tables, each row tagged with its transition number, and EMCY texts.

Used on both sides: the master (which controlword moves a drive towards a wanted state) and the
simulated drive (which state a received controlword leads to). Pure functions on ints, no I/O,
cheap enough for the cycle.
"""
from __future__ import annotations

# -- states -----------------------------------------------------------------------------------
NOT_READY = 0
SWITCH_ON_DISABLED = 1
READY_TO_SWITCH_ON = 2
SWITCHED_ON = 3
OPERATION_ENABLED = 4
QUICK_STOP_ACTIVE = 5
FAULT_REACTION_ACTIVE = 6
FAULT = 7
UNKNOWN = -1

STATE_NAMES = {
    NOT_READY: "Not ready to switch on",
    SWITCH_ON_DISABLED: "Switch on disabled",
    READY_TO_SWITCH_ON: "Ready to switch on",
    SWITCHED_ON: "Switched on",
    OPERATION_ENABLED: "Operation enabled",
    QUICK_STOP_ACTIVE: "Quick stop active",
    FAULT_REACTION_ACTIVE: "Fault reaction active",
    FAULT: "Fault",
    UNKNOWN: "Unknown",
}

#: statusword -> state: (mask, value, state), first match wins
STATUS_TABLE: tuple[tuple[int, int, int], ...] = (
    (0x004F, 0x0000, NOT_READY),
    (0x004F, 0x0040, SWITCH_ON_DISABLED),
    (0x006F, 0x0021, READY_TO_SWITCH_ON),
    (0x006F, 0x0023, SWITCHED_ON),
    (0x006F, 0x0027, OPERATION_ENABLED),
    (0x006F, 0x0007, QUICK_STOP_ACTIVE),
    (0x004F, 0x000F, FAULT_REACTION_ACTIVE),
    (0x004F, 0x0008, FAULT),
)

#: statusword bits a drive sets for each state (bits 0,1,2,3,5,6)
STATE_STATUS_BITS = {
    NOT_READY: 0x0000,
    SWITCH_ON_DISABLED: 0x0040,
    READY_TO_SWITCH_ON: 0x0021,
    SWITCHED_ON: 0x0023,
    OPERATION_ENABLED: 0x0027,
    QUICK_STOP_ACTIVE: 0x0007,
    FAULT_REACTION_ACTIVE: 0x000F,
    FAULT: 0x0008,
}

SW_READY_TO_SWITCH_ON = 1 << 0
SW_SWITCHED_ON = 1 << 1
SW_OPERATION_ENABLED = 1 << 2
SW_FAULT = 1 << 3
SW_VOLTAGE_ENABLED = 1 << 4
SW_QUICK_STOP = 1 << 5            #: 0 = quick stop active
SW_SWITCH_ON_DISABLED = 1 << 6
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9                #: controlword processed (drive not in local mode)
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11
SW_DRIVE_FOLLOWS = 1 << 12        #: CSP: drive follows the command value
SW_FOLLOWING_ERROR = 1 << 13      #: CSP: following error
#: statusword mask / value of Operation enabled (also in STATUS_TABLE)
SW_OP_ENABLED_MASK = 0x006F
SW_OP_ENABLED_VALUE = 0x0027

# -- controlword bits and commands (CiA 402 "device control commands") --------------------------
CW_BIT_SWITCH_ON = 1 << 0
CW_BIT_ENABLE_VOLTAGE = 1 << 1
CW_BIT_QUICK_STOP = 1 << 2        #: 0 = quick stop
CW_BIT_ENABLE_OPERATION = 1 << 3
CW_BIT_FAULT_RESET = 1 << 7       #: rising edge
CW_BIT_HALT = 1 << 8

CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_DISABLE_OPERATION = 0x0007     #: from Operation enabled: transition 5 (0x605C reaction, brake)
CW_ENABLE_OPERATION = 0x000F
CW_FAULT_RESET = 0x0080

CMD_SHUTDOWN = "shutdown"
CMD_SWITCH_ON = "switch on"
CMD_SWITCH_ON_ENABLE = "switch on + enable operation"
CMD_DISABLE_VOLTAGE = "disable voltage"
CMD_QUICK_STOP = "quick stop"
CMD_DISABLE_OPERATION = "disable operation"
CMD_ENABLE_OPERATION = "enable operation"
CMD_FAULT_RESET = "fault reset"

#: controlword -> command: (mask, value, command), first match wins (bit 7 handled apart)
COMMAND_TABLE: tuple[tuple[int, int, str], ...] = (
    (0x0082, 0x0000, CMD_DISABLE_VOLTAGE),
    (0x0086, 0x0002, CMD_QUICK_STOP),
    (0x0087, 0x0006, CMD_SHUTDOWN),
    (0x008F, 0x0007, CMD_SWITCH_ON),          # = disable operation from Operation enabled
    (0x008F, 0x000F, CMD_ENABLE_OPERATION),   # = switch on + enable from Ready to switch on
)

#: (transition number, from state, command, to state)  -- drive side, CiA 402 figure "state machine"
TRANSITIONS: tuple[tuple[int, int, str, int], ...] = (
    (2, SWITCH_ON_DISABLED, CMD_SHUTDOWN, READY_TO_SWITCH_ON),
    (3, READY_TO_SWITCH_ON, CMD_SWITCH_ON, SWITCHED_ON),
    (3, READY_TO_SWITCH_ON, CMD_ENABLE_OPERATION, SWITCHED_ON),   # 3 then 4 on the next evaluation
    (4, SWITCHED_ON, CMD_ENABLE_OPERATION, OPERATION_ENABLED),
    (5, OPERATION_ENABLED, CMD_SWITCH_ON, SWITCHED_ON),            # disable operation
    (6, SWITCHED_ON, CMD_SHUTDOWN, READY_TO_SWITCH_ON),
    (7, READY_TO_SWITCH_ON, CMD_QUICK_STOP, SWITCH_ON_DISABLED),
    (7, READY_TO_SWITCH_ON, CMD_DISABLE_VOLTAGE, SWITCH_ON_DISABLED),
    (8, OPERATION_ENABLED, CMD_SHUTDOWN, READY_TO_SWITCH_ON),
    (9, OPERATION_ENABLED, CMD_DISABLE_VOLTAGE, SWITCH_ON_DISABLED),
    (10, SWITCHED_ON, CMD_DISABLE_VOLTAGE, SWITCH_ON_DISABLED),
    (10, SWITCHED_ON, CMD_QUICK_STOP, SWITCH_ON_DISABLED),
    (11, OPERATION_ENABLED, CMD_QUICK_STOP, QUICK_STOP_ACTIVE),
    (12, QUICK_STOP_ACTIVE, CMD_DISABLE_VOLTAGE, SWITCH_ON_DISABLED),
    (16, QUICK_STOP_ACTIVE, CMD_ENABLE_OPERATION, OPERATION_ENABLED),
)
#: automatic transitions: 0 (power on -> Not ready), 1 (Not ready -> Switch on disabled),
#: 12 (Quick stop active -> Switch on disabled once stopped, quick stop option code 2),
#: 13 (any -> Fault reaction active on a fault), 14 (Fault reaction active -> Fault),
#: 15 (Fault -> Switch on disabled on a rising edge of controlword bit 7, "fault reset").
T_FAULT_RESET = 15
T_FAULT = 13
T_FAULT_DONE = 14
T_QUICK_STOP_DONE = 12

_TRANSITION_INDEX = {(frm, cmd): (num, to) for num, frm, cmd, to in TRANSITIONS}

#: THE walk (master side, also the hot loop through :func:`next_controlword`):
#: (transition number, from state, target state, controlword to send). A normal disable
#: (target Switch on disabled) goes through transition 5 (0x0007, "disable operation": the drive
#: stops per 0x605C and engages its holding brake) and then 10 (0x0000); never 9 from Operation
#: enabled. Quick stop is transition 11 (controlword bit 2 cleared).
WALK: tuple[tuple[int, int, int, int], ...] = (
    (15, FAULT, OPERATION_ENABLED, CW_FAULT_RESET),
    (2, SWITCH_ON_DISABLED, OPERATION_ENABLED, CW_SHUTDOWN),
    (3, READY_TO_SWITCH_ON, OPERATION_ENABLED, CW_SWITCH_ON),
    (4, SWITCHED_ON, OPERATION_ENABLED, CW_ENABLE_OPERATION),
    (16, QUICK_STOP_ACTIVE, OPERATION_ENABLED, CW_ENABLE_OPERATION),
    (15, FAULT, SWITCH_ON_DISABLED, CW_FAULT_RESET),
    (5, OPERATION_ENABLED, SWITCH_ON_DISABLED, CW_DISABLE_OPERATION),
    (10, SWITCHED_ON, SWITCH_ON_DISABLED, CW_DISABLE_VOLTAGE),
    (7, READY_TO_SWITCH_ON, SWITCH_ON_DISABLED, CW_DISABLE_VOLTAGE),
    (12, QUICK_STOP_ACTIVE, SWITCH_ON_DISABLED, CW_DISABLE_VOLTAGE),
    (5, OPERATION_ENABLED, SWITCHED_ON, CW_DISABLE_OPERATION),
    (3, READY_TO_SWITCH_ON, SWITCHED_ON, CW_SWITCH_ON),
    (2, SWITCH_ON_DISABLED, SWITCHED_ON, CW_SHUTDOWN),
    (15, FAULT, SWITCHED_ON, CW_FAULT_RESET),
    (11, OPERATION_ENABLED, QUICK_STOP_ACTIVE, CW_QUICK_STOP),
)
ENABLE_PATH = WALK      #: former name
_PATH_INDEX = {(frm, want): (num, cw) for num, frm, want, cw in WALK}


def state_from_status(statusword: int) -> int:
    """CiA 402 state of a statusword (``UNKNOWN`` if no row matches)."""
    for mask, value, state in STATUS_TABLE:
        if statusword & mask == value:
            return state
    return UNKNOWN


def state_name(state: int) -> str:
    return STATE_NAMES.get(state, f"state {state}")


def command_from_controlword(controlword: int) -> str | None:
    """Device control command of a controlword (fault reset bit 7 is an edge, see :func:`drive_step`)."""
    for mask, value, cmd in COMMAND_TABLE:
        if controlword & mask == value:
            return cmd
    return None


def drive_step(state: int, controlword: int, previous_controlword: int) -> tuple[int, int]:
    """Drive side: the state after receiving ``controlword`` -> (new state, transition number or 0)."""
    if state == FAULT:
        if controlword & 0x80 and not previous_controlword & 0x80:
            return SWITCH_ON_DISABLED, T_FAULT_RESET
        return state, 0
    if state in (FAULT_REACTION_ACTIVE, NOT_READY):
        return state, 0
    if controlword & 0x80:          # fault reset bit set outside Fault: no device control command
        return state, 0
    cmd = command_from_controlword(controlword)
    hit = _TRANSITION_INDEX.get((state, cmd)) if cmd else None
    if hit is None:
        return state, 0
    num, to = hit
    return to, num


def controlword_towards(state: int, wanted: int, previous_controlword: int = 0) -> tuple[int, int]:
    """Master side: (controlword, transition number) for the next step from ``state`` to ``wanted``.

    Returns ``(previous_controlword, 0)`` when already there or when no step leads there
    (Not ready to switch on, Fault reaction active: wait). A fault reset is an edge: after a
    controlword with bit 7 set, the next call from Fault returns bit 7 cleared first.
    """
    if state == wanted:
        return previous_controlword & ~0x80, 0
    hit = _PATH_INDEX.get((state, wanted))
    if hit is None:
        return previous_controlword, 0
    num, cw = hit
    if cw & 0x80 and previous_controlword & 0x80:
        return previous_controlword & ~0x80, 0      # re-arm the rising edge
    return cw, num


def next_controlword(statusword: int, target: int, previous_controlword: int) -> int:
    """THE CiA 402 walk as one pure function: the controlword to send now so that a drive whose
    last statusword is ``statusword`` moves one transition towards ``target`` (a state constant:
    ``OPERATION_ENABLED``, ``SWITCH_ON_DISABLED``, ``SWITCHED_ON``, ``QUICK_STOP_ACTIVE``).

    ``statusword < 0`` (none received yet), Not ready to switch on, Fault reaction active, or
    already there: ``previous_controlword`` (with bit 7 cleared once there). Fault reset is a
    rising edge: after a controlword with bit 7 the next call from Fault returns 0x0000 first.
    No allocation; for the hot loop (``hexacnc/daemon/loop.py``), the master and the tests.
    """
    if statusword < 0:
        return previous_controlword
    return controlword_towards(state_from_status(statusword), target, previous_controlword)[0]


def drive_statusword(state: int, remote: bool = True) -> int:
    """Drive side: the statusword bits 0..6 (+ voltage enabled bit 4 where the power stage is on,
    + remote bit 9) of a state; the simulated drives add the mode-specific bits 10..13."""
    sw = STATE_STATUS_BITS.get(state, 0) | (SW_REMOTE if remote else 0)
    if state in (READY_TO_SWITCH_ON, SWITCHED_ON, OPERATION_ENABLED, QUICK_STOP_ACTIVE):
        sw |= SW_VOLTAGE_ENABLED
    return sw


def is_operation_enabled(statusword: int) -> bool:
    return statusword >= 0 and statusword & SW_OP_ENABLED_MASK == SW_OP_ENABLED_VALUE


def status_problem(statusword: int, csp: bool = True) -> str | None:
    """What is wrong with the statusword of a drive that should be following in Operation
    enabled: None when fine, else a short text (remote bit 9 lost, bit 12 "drive follows the
    command value" clear in CSP, following error bit 13, not Operation enabled)."""
    if not is_operation_enabled(statusword):
        return f"left Operation enabled ({status_text(statusword)})"
    if not statusword & SW_REMOTE:
        return "remote (statusword bit 9) lost: the drive no longer processes the controlword"
    if csp and not statusword & SW_DRIVE_FOLLOWS:
        return "statusword bit 12 clear: the drive does not follow the command value"
    if csp and statusword & SW_FOLLOWING_ERROR:
        return "statusword bit 13: following error"
    return None


# -- option codes (0x605A quick stop, 0x605C disable operation, 0x605E fault reaction, 0x6007) ----
QS_SLOW_DOWN_DISABLE = 1          #: 0x605A: slow down ramp (0x6084), then Switch on disabled
QS_QUICK_RAMP_DISABLE = 2         #: 0x605A: quick stop ramp (0x6085), then Switch on disabled
QS_SLOW_DOWN_STAY = 5             #: 0x605A: slow down ramp, stay in Quick stop active
QS_QUICK_RAMP_STAY = 6            #: 0x605A: quick stop ramp, stay in Quick stop active
DISABLE_OP_COAST = 0              #: 0x605C: disable the drive function at once
DISABLE_OP_SLOW_DOWN = 1          #: 0x605C: slow down ramp (0x6084), then disable
FAULT_REACTION_COAST = 0          #: 0x605E: disable drive, motor free
FAULT_REACTION_SLOW_DOWN = 1      #: 0x605E: slow down ramp
FAULT_REACTION_QUICK_RAMP = 2     #: 0x605E: quick stop ramp
ABORT_NONE = 0                    #: 0x6007 abort connection option: no action
ABORT_FAULT = 1                   #: 0x6007: fault (then 0x605E)
ABORT_DISABLE_VOLTAGE = 2         #: 0x6007: disable voltage command
ABORT_QUICK_STOP = 3              #: 0x6007: quick stop command (then 0x605A)
COMM_ERROR_PRE_OPERATIONAL = 0    #: 0x1029:1 communication error: NMT pre-operational
COMM_ERROR_NO_CHANGE = 1          #: 0x1029:1: NMT state unchanged
COMM_ERROR_STOPPED = 2            #: 0x1029:1: NMT stopped

EMCY_RPDO_TIMEOUT = 0x8250
EMCY_SYNC_LOSS = 0x8700           #: "sync controller" (no SYNC within 0x1006 x 1.5 + margin)


# -- modes of operation ---------------------------------------------------------------------------
MODE_PROFILE_POSITION = 1
MODE_PROFILE_VELOCITY = 3
MODE_HOMING = 6
MODE_CSP = 8
MODE_CSV = 9
MODE_CST = 10

# -- EMCY -----------------------------------------------------------------------------------------
EMCY_FOLLOWING_ERROR = 0x8611
EMCY_HEARTBEAT = 0x8130

#: error code -> text (CiA 301 / CiA 402); lookup falls back to the 0xFFF0, 0xFF00, 0xF000 class
EMCY_CODES: dict[int, str] = {
    0x0000: "error reset or no error",
    0x1000: "generic error",
    0x2000: "current",
    0x2100: "current, device input side",
    0x2200: "current inside the device",
    0x2300: "current, device output side",
    0x2310: "continuous over-current",
    0x2320: "short circuit / earth leakage",
    0x2330: "earth leakage",
    0x2340: "short circuit",
    0x3000: "voltage",
    0x3100: "mains voltage",
    0x3110: "mains over-voltage",
    0x3120: "mains under-voltage",
    0x3130: "phase failure",
    0x3200: "voltage inside the device",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x3300: "output voltage",
    0x4000: "temperature",
    0x4100: "ambient temperature",
    0x4200: "device temperature",
    0x4210: "excess temperature device",
    0x4300: "drive temperature",
    0x4310: "excess temperature drive (motor)",
    0x5000: "device hardware",
    0x5100: "supply",
    0x5500: "data storage",
    0x6000: "device software",
    0x6100: "internal software",
    0x6200: "user software",
    0x6300: "data set",
    0x6320: "parameter error",
    0x7000: "additional modules",
    0x7100: "power",
    0x7120: "motor",
    0x7121: "motor blocked",
    0x7300: "sensor",
    0x7305: "incremental sensor 1 fault",
    0x7310: "speed",
    0x7320: "position (encoder)",
    0x8000: "monitoring",
    0x8100: "communication",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error",
    0x8140: "recovered from bus off",
    0x8150: "CAN-ID collision",
    0x8200: "protocol error",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8230: "DAM MPDO not processed, destination object not available",
    0x8240: "unexpected SYNC data length",
    0x8250: "RPDO timeout",
    0x8300: "torque control",
    0x8400: "velocity speed controller",
    0x8500: "position controller",
    0x8600: "positioning controller",
    0x8611: "following error",
    0x8612: "reference limit",
    0x8700: "sync controller",
    0x9000: "external error",
    0xF000: "additional functions",
    0xFF00: "device specific",
}

#: error register (0x1001) bits
ERROR_REGISTER_BITS = ("generic", "current", "voltage", "temperature", "communication",
                       "device profile", "reserved", "manufacturer")


def emcy_text(code: int, register: int = 0, data: bytes = b"") -> str:
    """Readable text of an EMCY: ``'0x8611 following error [generic, device profile]'``."""
    text = EMCY_CODES.get(code)
    if text is None:
        if code >= 0xFF00:
            text = "device specific"
        else:
            for mask in (0xFFF0, 0xFF00, 0xF000):
                if code & mask in EMCY_CODES:
                    text = EMCY_CODES[code & mask]
                    break
            else:
                text = "unknown error"
    bits = [name for b, name in enumerate(ERROR_REGISTER_BITS) if register >> b & 1]
    out = f"0x{code:04X} {text}"
    if bits:
        out += f" [{', '.join(bits)}]"
    if data and any(data):
        out += f" data {bytes(data).hex()}"
    return out


def status_text(statusword: int) -> str:
    """Readable statusword: state name plus the set flags."""
    flags = [name for bit, name in ((SW_WARNING, "warning"), (SW_TARGET_REACHED, "target reached"),
                                    (SW_INTERNAL_LIMIT, "internal limit active"),
                                    (SW_DRIVE_FOLLOWS, "follows command"),
                                    (SW_FOLLOWING_ERROR, "following error")) if statusword & bit]
    s = f"{state_name(state_from_status(statusword))} (0x{statusword:04X})"
    return s + (": " + ", ".join(flags) if flags else "")
