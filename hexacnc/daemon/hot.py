"""``python -m hexacnc.daemon.hot FD``: the hot loop process.

Started by the supervisor with :mod:`subprocess` (a fresh interpreter: nothing of the
supervisor - threads, sockets, the planner, the parent's ``__main__`` - is imported here).
Reads its arguments as one pickle from stdin, reports "ready"/"error" as one JSON line on
the pipe ``FD``, then runs :func:`hexacnc.daemon.loop.hot_main`.
"""
from __future__ import annotations

import json
import os
import pickle
import sys


def main() -> int:
    import signal
    from .loop import install_signal_handlers, set_parent_death_signal
    # before anything slow: Ctrl-C in the terminal reaches the whole process group, and the hot loop
    # must not die before the supervisor orders the stop; the kernel tells us when the supervisor dies
    install_signal_handlers(signal.SIGUSR1)
    set_parent_death_signal(signal.SIGUSR1)
    fd = int(sys.argv[1])
    args = pickle.load(sys.stdin.buffer)
    sys.stdin.close()
    out = os.fdopen(fd, "w")

    def report(kind: str, payload) -> None:
        out.write(json.dumps([kind, payload], default=str) + "\n")
        out.flush()
        out.close()

    from .loop import hot_main
    hot_main(args["cfg"], args["shm"], args["io_mode"], args["period_s"], args["realtime"],
             args["log_level"], report, args.get("sim_args"), args.get("cpu"), signal.SIGUSR1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
