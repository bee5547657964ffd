"""Result codes of the per-cycle transform (:class:`hexacnc.transform.CycleTransform`).

One place for the integers that the cycle's ``command``/``feedback`` return, shared by the
generic routine and the generated unrolled code (:mod:`hexacnc.cyclegen`), which refers to them
by name.
"""
from __future__ import annotations

OK = 0
LIMIT_LENGTH = 1          #: a strut length outside [min_length_mm, max_length_mm]
LIMIT_JOINT = 2           #: a joint angle beyond its cone
LIMIT_VELOCITY = 3        #: the step to the command exceeds the strut velocity guard
LIMIT_ACCELERATION = 4    #: the step's change exceeds the strut acceleration guard
LIMIT_SINGULAR = 5        #: the Jacobian is (near) singular
LIMIT_INPUT = 6           #: a pose value that is not finite
FK_NOT_CONVERGED = 7      #: forward kinematics did not converge
LIMIT_CALIBRATION = 8     #: the calibrated reading map has no solution for the command

#: every code by name, for the generated code's namespace
CODES = {name: value for name, value in globals().items() if name.isupper() and isinstance(value, int)}
