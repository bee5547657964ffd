"""Calibration and model diagnosis from measured data.

Modules: :mod:`.measurements` (CSV contract, column mappings), :mod:`.model`
(measurement model: geometry, frames, cause models), :mod:`.identify`
(weighted Levenberg-Marquardt, covariance, unidentifiable directions),
:mod:`.plan` (observability-optimal poses), :mod:`.diagnose` (cause selection),
:mod:`.synth` (seeded synthetic sets), :mod:`.report`/:mod:`.plots`/:mod:`.output`.
"""
from __future__ import annotations

import ctypes


def limit_blas_threads(n: int = 1) -> bool:
    """Use ``n`` BLAS threads: the fits work on small matrices where extra threads only add
    synchronisation (and stall badly when another process owns a core).  True if applied."""
    done = False
    try:
        with open("/proc/self/maps", encoding="utf-8") as f:
            libs = {ln.split()[-1] for ln in f if len(ln.split()) >= 6 and "openblas" in ln.split()[-1].lower()}
    except OSError:
        return False
    for path in libs:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for sym in ("scipy_openblas_set_num_threads64_", "openblas_set_num_threads64_",
                    "openblas_set_num_threads", "scipy_openblas_set_num_threads"):
            fn = getattr(lib, sym, None)
            if fn is not None:
                fn(ctypes.c_int(n))
                done = True
                break
    return done
