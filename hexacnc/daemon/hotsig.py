"""Signals of the hot process: what ends it, and how it learns that the supervisor is gone.

The handlers only set :data:`SIGNALS`; the cycle (:meth:`HotLoop._check_signals`) acts on them.
"""
from __future__ import annotations

#: set by the signal handlers of the hot process (:func:`install_signal_handlers`): [0] the signal
#: that asks for a controlled stop (SIGTERM, SIGHUP), [1] 1 once the parent-death signal came
SIGNALS = [0, 0]


def install_signal_handlers(pdeath_signal: int | None = None) -> None:
    """Hot process: SIGINT ignored (Ctrl-C reaches the whole process group: the supervisor orders
    the stop), SIGTERM/SIGHUP ask the loop for a controlled stop and exit, ``pdeath_signal`` (the
    kernel sends it when the supervisor dies, see :func:`set_parent_death_signal`) marks it gone.
    The handlers only set :data:`SIGNALS`; the cycle acts on them."""
    import signal

    def ask_stop(signum, frame):
        SIGNALS[0] = signum

    def parent_died(signum, frame):
        SIGNALS[1] = 1

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, ask_stop)
    signal.signal(signal.SIGHUP, ask_stop)
    if pdeath_signal:
        signal.signal(pdeath_signal, parent_died)


def set_parent_death_signal(signum: int) -> bool:
    """``prctl(PR_SET_PDEATHSIG, signum)``: the kernel signals this process when its parent dies
    (Linux; False where unavailable - the periodic ``getppid`` check remains)."""
    try:
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(1, int(signum), 0, 0, 0) == 0     # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        return False
