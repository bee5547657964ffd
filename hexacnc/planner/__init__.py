"""Look-ahead planner: motion blocks -> time-parameterised platform setpoints within strut and joint limits.

``plan_program(blocks, cfg, hexapod=None, period_s=None) -> Plan``; ``Plan.sampler(period_s)`` for the daemon.
"""
from .plan import (FLAG_DWELL, FLAG_END, FLAG_EVENT, FLAG_MOTION, FLAG_PAUSED, FLAG_PROGRAM_PAUSE, FLAG_RAPID,
                   FLAG_STOPPING, Plan, plan_program)

__all__ = ["plan_program", "Plan", "FLAG_MOTION", "FLAG_RAPID", "FLAG_DWELL", "FLAG_PROGRAM_PAUSE", "FLAG_PAUSED",
           "FLAG_STOPPING", "FLAG_END", "FLAG_EVENT"]
