"""Decode a session capture (``hexacnc run --capture``) with an independent CANopen dissector
(tshark, Wireshark's command line) and summarise it::

    python -m drivers.pcapcheck FILE.pcap [FILE-bus1.pcap ...]   # JSON on stdout

Per file: frames, malformed frames (``_ws.malformed``), expert warnings, SDO aborts (object, code),
objects written (SDO download initiate) and read (upload initiate) per node, EMCY codes per node,
NMT commands, the controlword values seen in SDO downloads of 0x6040 and in RPDO2 (0x300 + node, changes) per node. Exit code 0
when no file has a malformed frame or an SDO abort, 1 otherwise, 2 when tshark is missing.
tshark is told to decode CAN as CANopen with ``-d can.subdissector,canopen``.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections import Counter, defaultdict

FIELDS = ("frame.number", "can.id", "canopen.function_code", "canopen.node_id", "canopen.sdo.ccs",
          "canopen.sdo.scs", "canopen.sdo.main_idx", "canopen.sdo.sub_idx", "canopen.sdo.abort_code",
          "canopen.sdo.data.bytes", "canopen.em.err_code", "canopen.nmt_ctrl.cd", "canopen.nmt_ctrl.node_id",
          "canopen.pdo.data.bytes", "_ws.malformed", "_ws.expert.severity")


def tshark_available() -> bool:
    return shutil.which("tshark") is not None


def _int(v: str) -> int | None:
    v = v.split(",")[0].strip()
    if not v:
        return None
    try:
        return int(v, 0)
    except ValueError:
        try:
            return int(v, 16)
        except ValueError:
            return None


def check(path: str, timeout_s: float = 600.0) -> dict:
    """Summary of one pcap decoded by tshark (see module doc)."""
    cmd = ["tshark", "-n", "-r", path, "-d", "can.subdissector,canopen", "-T", "fields", "-E", "separator=\t",
           "-E", "occurrence=f"] + [x for f in FIELDS for x in ("-e", f)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    if r.returncode != 0:
        raise RuntimeError(f"tshark failed on {path}: {r.stderr.strip()[-500:]}")
    frames = malformed = warnings = 0
    aborts, written, read = [], defaultdict(set), defaultdict(set)
    emcy, nmt, cw = defaultdict(Counter), Counter(), defaultdict(list)
    cw_pdo = defaultdict(list)
    for line in r.stdout.splitlines():
        f = dict(zip(FIELDS, line.split("\t") + [""] * len(FIELDS)))
        frames += 1
        if f["_ws.malformed"]:
            malformed += 1
        sev = _int(f["_ws.expert.severity"])
        if sev is not None and sev >= 0x00600000:       # PI_WARN and above
            warnings += 1
        can_id = _int(f["can.id"]) or 0
        node = can_id & 0x7F
        idx, sub = _int(f["canopen.sdo.main_idx"]), _int(f["canopen.sdo.sub_idx"])
        if f["canopen.sdo.abort_code"]:
            aborts.append({"frame": _int(f["frame.number"]), "node": node, "object": f"0x{idx or 0:04X}:{sub or 0}",
                           "code": f["canopen.sdo.abort_code"]})
        if 0x600 <= can_id <= 0x67F and idx is not None:
            ccs = _int(f["canopen.sdo.ccs"])
            key = f"0x{idx:04X}:{sub or 0}"
            if ccs == 1:
                written[node].add(key)
                if idx == 0x6040:
                    data = f["canopen.sdo.data.bytes"].replace(":", "")
                    if data:
                        cw[node].append(int.from_bytes(bytes.fromhex(data)[:2], "little"))
            elif ccs == 2:
                read[node].add(key)
        if 0x301 <= can_id <= 0x37F and f["canopen.pdo.data.bytes"]:      # RPDO2: controlword events
            data = bytes.fromhex(f["canopen.pdo.data.bytes"].replace(":", ""))
            if len(data) == 2:
                v = int.from_bytes(data, "little")
                if not cw_pdo[node] or cw_pdo[node][-1] != v:
                    cw_pdo[node].append(v)
        if 0x081 <= can_id <= 0x0FF and f["canopen.em.err_code"]:
            emcy[node][f["canopen.em.err_code"]] += 1
        if can_id == 0 and f["canopen.nmt_ctrl.cd"]:
            nmt[f["canopen.nmt_ctrl.cd"]] += 1
    return {"file": path, "frames": frames, "malformed": malformed, "expert_warnings": warnings,
            "sdo_aborts": aborts, "written": {n: sorted(v) for n, v in sorted(written.items())},
            "read": {n: sorted(v) for n, v in sorted(read.items())},
            "emcy": {n: dict(c) for n, c in sorted(emcy.items())}, "nmt_commands": dict(nmt),
            "controlwords_by_sdo": {n: v for n, v in sorted(cw.items())},
            "controlwords_by_rpdo2": {n: v for n, v in sorted(cw_pdo.items())}}


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv:
        print(__doc__, file=sys.stderr)
        return 2
    if not tshark_available():
        print("pcapcheck: tshark is not installed (apt-get install tshark)", file=sys.stderr)
        return 2
    out = [check(p) for p in argv]
    print(json.dumps(out, indent=1))
    return 0 if all(o["malformed"] == 0 and not o["sdo_aborts"] for o in out) else 1


if __name__ == "__main__":
    raise SystemExit(main())
