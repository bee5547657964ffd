"""CiA 402 tables: every tagged transition, the enable/disable walks, statusword decoding, EMCY texts."""
import pytest

from drivers import cia402 as c

CW_FOR = {c.CMD_SHUTDOWN: c.CW_SHUTDOWN, c.CMD_SWITCH_ON: c.CW_SWITCH_ON, c.CMD_ENABLE_OPERATION: c.CW_ENABLE_OPERATION,
          c.CMD_DISABLE_VOLTAGE: c.CW_DISABLE_VOLTAGE, c.CMD_QUICK_STOP: c.CW_QUICK_STOP}


@pytest.mark.parametrize("row", c.TRANSITIONS, ids=lambda r: f"T{r[0]}-{r[2]}")
def test_each_transition_row(row):
    num, frm, cmd, to = row
    cw = CW_FOR[cmd]
    assert c.command_from_controlword(cw) == cmd
    assert c.drive_step(frm, cw, 0) == (to, num)
    # the statusword of the target state decodes back to it
    assert c.state_from_status(c.STATE_STATUS_BITS[to] | c.SW_REMOTE | c.SW_VOLTAGE_ENABLED) == to


def test_transition_numbers_cover_cia402():
    nums = {r[0] for r in c.TRANSITIONS}
    assert nums == {2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 16}


def test_irrelevant_commands_do_nothing():
    assert c.drive_step(c.SWITCH_ON_DISABLED, c.CW_ENABLE_OPERATION, 0) == (c.SWITCH_ON_DISABLED, 0)
    assert c.drive_step(c.FAULT, c.CW_ENABLE_OPERATION, 0) == (c.FAULT, 0)
    assert c.drive_step(c.OPERATION_ENABLED, c.CW_ENABLE_OPERATION, 0) == (c.OPERATION_ENABLED, 0)


def test_fault_reset_is_a_rising_edge():
    assert c.drive_step(c.FAULT, 0x80, 0x00) == (c.SWITCH_ON_DISABLED, 15)
    assert c.drive_step(c.FAULT, 0x80, 0x80) == (c.FAULT, 0)
    cw, t = c.controlword_towards(c.FAULT, c.OPERATION_ENABLED, 0x80)
    assert cw & 0x80 == 0 and t == 0          # re-arm the edge first
    assert c.controlword_towards(c.FAULT, c.OPERATION_ENABLED, cw) == (0x80, 15)


@pytest.mark.parametrize("start", [c.FAULT, c.SWITCH_ON_DISABLED, c.READY_TO_SWITCH_ON, c.SWITCHED_ON,
                                   c.QUICK_STOP_ACTIVE])
@pytest.mark.parametrize("wanted", [c.OPERATION_ENABLED, c.SWITCH_ON_DISABLED])
def test_master_walk_reaches_wanted_state(start, wanted):
    state, cw, path = start, 0, []
    for _ in range(8):
        if state == wanted:
            break
        cw2, t = c.controlword_towards(state, wanted, cw)
        new, num = c.drive_step(state, cw2, cw)
        if t:
            assert num == t, f"master expects transition {t}, drive made {num}"
            path.append(t)
        state, cw = new, cw2
    assert state == wanted, (start, wanted, path)
    if start == c.SWITCH_ON_DISABLED and wanted == c.OPERATION_ENABLED:
        assert path == [2, 3, 4]


def test_statusword_decoding_ignores_other_bits():
    for state, bits in c.STATE_STATUS_BITS.items():
        assert c.state_from_status(bits) == state
        assert c.state_from_status(bits | 0xFF90) == state      # bits 4, 7..15 never decide the state
    assert c.state_from_status(0x1637) == c.OPERATION_ENABLED
    assert c.state_from_status(0x0250) == c.SWITCH_ON_DISABLED
    assert c.state_from_status(0x0218) == c.FAULT
    assert "following error" in c.status_text(0x2237)


def test_emcy_texts():
    assert c.emcy_text(0x8611, 0x21) == "0x8611 following error [generic, device profile]"
    assert c.emcy_text(0x8130, 0x11).startswith("0x8130 life guard or heartbeat error [generic, communication]")
    assert c.emcy_text(0x3210) == "0x3210 DC link over-voltage"
    assert c.emcy_text(0x4310, 0x09) == "0x4310 excess temperature drive (motor) [generic, temperature]"
    assert c.emcy_text(0x2311) == "0x2311 continuous over-current"      # class fallback 0x2310
    assert c.emcy_text(0x5432) == "0x5432 device hardware"
    assert c.emcy_text(0xFF12) == "0xFF12 device specific"
    assert c.emcy_text(0x0000) == "0x0000 error reset or no error"
    assert c.emcy_text(0x1000, 1, b"\x01\x02\0\0\0").endswith("data 0102000000")


def test_next_controlword_is_the_walk_from_statuswords():
    sw = {s: c.drive_statusword(s) for s in c.STATE_STATUS_BITS}
    assert c.next_controlword(-1, c.OPERATION_ENABLED, 0x1234) == 0x1234          # nothing heard yet
    assert c.next_controlword(sw[c.SWITCH_ON_DISABLED], c.OPERATION_ENABLED, 0) == c.CW_SHUTDOWN
    assert c.next_controlword(sw[c.READY_TO_SWITCH_ON], c.OPERATION_ENABLED, 6) == c.CW_SWITCH_ON
    assert c.next_controlword(sw[c.SWITCHED_ON], c.OPERATION_ENABLED, 7) == c.CW_ENABLE_OPERATION
    assert c.next_controlword(sw[c.OPERATION_ENABLED], c.OPERATION_ENABLED, 0x0F) == 0x0F
    # normal disable: transition 5 (0x0007, ramp per 0x605C, brake) then 10 (0x0000), never 9
    assert c.next_controlword(sw[c.OPERATION_ENABLED], c.SWITCH_ON_DISABLED, 0x0F) == c.CW_DISABLE_OPERATION == 0x0007
    assert c.next_controlword(sw[c.SWITCHED_ON], c.SWITCH_ON_DISABLED, 0x07) == c.CW_DISABLE_VOLTAGE
    assert c.next_controlword(sw[c.OPERATION_ENABLED], c.QUICK_STOP_ACTIVE, 0x0F) == c.CW_QUICK_STOP
    assert not c.CW_QUICK_STOP & c.CW_BIT_QUICK_STOP                                 # bit 2 cleared
    assert c.next_controlword(sw[c.FAULT], c.OPERATION_ENABLED, 0) == c.CW_FAULT_RESET
    assert c.next_controlword(sw[c.FAULT], c.OPERATION_ENABLED, c.CW_FAULT_RESET) == 0   # re-arm the edge
    assert c.next_controlword(sw[c.FAULT_REACTION_ACTIVE], c.OPERATION_ENABLED, 0x0F) == 0x0F   # wait


def test_status_problem_names_bits_9_12_13():
    ok = c.drive_statusword(c.OPERATION_ENABLED) | c.SW_DRIVE_FOLLOWS
    assert c.status_problem(ok) is None
    assert "bit 9" in c.status_problem(ok & ~c.SW_REMOTE)
    assert "bit 12" in c.status_problem(ok & ~c.SW_DRIVE_FOLLOWS)
    assert "bit 13" in c.status_problem(ok | c.SW_FOLLOWING_ERROR)
    assert "left Operation enabled" in c.status_problem(c.drive_statusword(c.QUICK_STOP_ACTIVE))
