"""G and M codes of the interpreter: modal groups, and names of what is refused.

G codes are kept x10 (G59.1 -> 591).  A code absent from the groups is
refused with ``unsupported`` naming it (LinuxCNC's name for the feature).
"""
from __future__ import annotations

#: modal group of each supported G code (0: non-modal)
G_GROUP = {0: 1, 10: 1, 20: 1, 30: 1, 50: 1, 51: 1, 70: 15, 382: 1, 383: 1, 384: 1, 385: 1, 730: 1, 800: 1, 810: 1, 820: 1,
           830: 1, 840: 1, 850: 1, 860: 1, 890: 1,
           170: 2, 180: 2, 190: 2,
           900: 3, 910: 3, 901: 4, 911: 4, 930: 5, 940: 5, 200: 6, 210: 6, 400: 7, 410: 7, 411: 7, 420: 7, 421: 7,
           430: 8, 490: 8, 980: 10, 990: 10,
           540: 12, 550: 12, 560: 12, 570: 12, 580: 12, 590: 12, 591: 12, 592: 12, 593: 12,
           610: 13, 611: 13, 640: 13, 80: 15,
           431: 8, 432: 8,
           40: 0, 100: 0, 520: 0, 530: 0, 920: 0, 921: 0, 922: 0, 923: 0, 280: 0, 281: 0, 300: 0, 301: 0}
#: canned cycles (motion group)
CYCLES = frozenset({730, 810, 820, 830, 840, 850, 860, 890})
#: straight probes
PROBES = frozenset({382, 383, 384, 385})
G_UNSUPPORTED = {
    52: "G5.2 NURBS", 53: "G5.3 NURBS end",
    330: "G33 spindle-synchronised motion",
    331: "G33.1 rigid tapping (needs spindle-synchronised motion)",
    760: "G76 lathe threading cycle (a lathe cycle: no spindle-synchronised motion on a hexapod)",
    870: "G87 back boring cycle (needs spindle orientation M19)",
    880: "G88 boring cycle with manual retract (needs an operator jog during the program)",
    740: "G74 left-hand tapping cycle", 700: "G70 lathe finishing cycle", 710: "G71 lathe roughing cycle",
    711: "G71.1 lathe roughing cycle", 712: "G71.2 lathe roughing cycle", 720: "G72 lathe facing cycle",
    721: "G72.1 lathe facing cycle", 722: "G72.2 lathe facing cycle",
    950: "G95 feed per revolution", 960: "G96 constant surface speed", 970: "G97 spindle RPM mode",
    171: "G17.1 UV plane", 181: "G18.1 WU plane", 191: "G19.1 VW plane",
    612: "G61.2", 641: "G64.1", 211: "G21.1", 201: "G20.1", 60: "G6 spline",
    621: "G62.1", 910 + 2: "G91.2",
}
#: M codes: modal group (4 stops, 6 tool change, 7 spindle, 8 coolant, 5 I/O, 10 state)
M_GROUP = {0: 4, 1: 4, 2: 4, 30: 4, 6: 6, 61: 6, 3: 7, 4: 7, 5: 7, 7: 8, 8: 8, 9: 8,
           62: 5, 63: 5, 64: 5, 65: 5, 66: 5, 67: 5, 68: 5, 70: 10, 71: 10, 72: 10, 73: 10}
M_UNSUPPORTED = {
    19: "M19 spindle orientation", 48: "M48 override enable", 49: "M49 override disable",
    50: "M50 feed override control", 51: "M51 spindle override control",
    52: "M52 adaptive feed", 53: "M53 feed stop", 60: "M60 pallet change",
    98: "M98 Fanuc-style subroutine call", 99: "M99 Fanuc-style subroutine return",
}
