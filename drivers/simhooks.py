"""Extension hooks of the simulated drives: an object-dictionary callback registry per drive
(:class:`OdHooks`, ``drive.hooks``) and the list of extensions attached to every new drive
(:data:`EXTENSIONS`). Homing, touch probe and similar simulated features live in their own
modules and register here; :mod:`drivers.simnode` calls the hooks.

Example (a module imported before the drives are built, e.g. from :mod:`drivers.simdrive`)::

    from drivers import simhooks

    def attach(drive):
        drive.hooks.on_read(0x60B9, lambda sub: drive.probe_status)
        drive.hooks.on_write(0x60B8, lambda sub, value: ...)
        drive.hooks.on_sync(lambda drive, now_s: ...)

    simhooks.EXTENSIONS.append(attach)
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from .simnode import SimDrive


class OdHooks:
    """Object-dictionary callback registry of one simulated drive.

    * ``on_read(index, fn)``: ``fn(subindex) -> int | None`` answers SDO reads of ``index`` (None:
      fall through to the drive / the stored value); PDO getters use it too (sub 0);
    * ``on_write(index, fn)``: ``fn(subindex, value)`` after an SDO or RPDO write of ``index`` (raise
      ``canopen.sdo.SdoAbortedError(code)`` to refuse an SDO write);
    * ``on_sync(fn)``: ``fn(drive, now_s)`` after each SYNC step; ``on_controlword(fn)``:
      ``fn(drive, controlword)`` before the state machine sees a controlword (mode-specific bits);
      ``on_status(fn)``: ``fn(drive) -> int`` statusword bits ORed in (mode-specific bits).
    """

    def __init__(self):
        self.read: dict[int, Callable] = {}
        self.write: dict[int, list[Callable]] = {}
        self.sync: list[Callable] = []
        self.controlword: list[Callable] = []
        self.status: list[Callable] = []

    def on_read(self, index: int, fn: Callable) -> None:
        self.read[index] = fn

    def on_write(self, index: int, fn: Callable) -> None:
        self.write.setdefault(index, []).append(fn)

    def on_sync(self, fn: Callable) -> None:
        self.sync.append(fn)

    def on_controlword(self, fn: Callable) -> None:
        self.controlword.append(fn)

    def on_status(self, fn: Callable) -> None:
        """``fn(drive) -> int``: statusword bits ORed into the drive's statusword (mode-specific)."""
        self.status.append(fn)


#: ``fn(drive)`` called for every new :class:`SimDrive` (after its own set-up): register hooks here,
#: e.g. ``simhooks.EXTENSIONS.append(homing.attach)`` in the extension module (imported by simdrive)
EXTENSIONS: list[Callable[["SimDrive"], None]] = []
