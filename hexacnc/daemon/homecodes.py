"""Result codes and time-outs of the hot loop's CiA 402 homing (:mod:`.homeloop`), shared with
:mod:`.faults` and :mod:`.operator` (``H_HOME_RESULT`` in the shared header)."""

#: the whole homing run (all struts) must end within this (s)
HOME_TIMEOUT_S = 45.0
#: an SDO answer must come within this (s)
SDO_TIMEOUT_S = 0.5

RUNNING, DONE = 1, 2
(E_UNSUPPORTED, E_SDO_ABORT, E_SDO_TIMEOUT, E_HOMING_ERROR, E_FAULT, E_LIMIT, E_TIMEOUT, E_ABORTED,
 E_HEARTBEAT) = range(-1, -10, -1)
ERROR_TEXT = {E_UNSUPPORTED: "this bus mode has no SDO channel (inproc simulation)",
              E_SDO_ABORT: "the drive refused an SDO write (abort)",
              E_SDO_TIMEOUT: "no SDO answer",
              E_HOMING_ERROR: "the drive reports a homing error (statusword bit 13)",
              E_FAULT: "the drive faulted or left Operation enabled while homing",
              E_HEARTBEAT: "the drive's heartbeat was lost while homing",
              E_LIMIT: "a measured strut length left the strut limits while homing",
              E_TIMEOUT: f"homing did not finish within {HOME_TIMEOUT_S:g} s",
              E_ABORTED: "homing was stopped (stop, disable or shutdown)"}
