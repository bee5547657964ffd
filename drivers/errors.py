"""Errors of the drive layer - and the root of the whole controller's error hierarchy.

The root lives here, in the bottom layer, so that ``drivers`` depends on nothing in ``hexacnc``
while one ``except HexacncError`` (``hexacnc.errors`` re-exports these classes under the same
names) still covers both layers. Every message names what is wrong and where (node, object,
strut, file, key).
"""
from __future__ import annotations


class ControlError(Exception):
    """Base of all errors of the controller (``hexacnc.errors.HexacncError`` is this class)."""


class ConfigError(ControlError):
    """A machine or drive description is malformed or out of range."""


class BusError(ControlError):
    """The drive bus or a drive misbehaves, or a bus layout does not fit."""
