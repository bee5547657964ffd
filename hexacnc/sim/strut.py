"""Coupled strut dynamics for simulated drives (``drivers/simdrive.py`` model plug-in).

:class:`CoupledStruts` steps all six struts of the coupled model
(:mod:`hexacnc.sim.dynamics`) along the commands it receives: error
coordinates about the commanded motion, inertial loads from the commands'
second difference (drive side ``m_d r''``, carrier ``M J^-1 r''``), Jacobian and
mass matrix re-evaluated every ``update_s`` at the pose found by forward
kinematics of the commands (warm-started).  ``step(cmd_mm (6,), dt_s)``
returns the drive-side positions (what each drive's encoder reads, mm);
``length_mm`` holds the true strut lengths (spring deflection included).

For :class:`drivers.simdrive.SimDrives`, which steps each drive on its own
(``StrutModel``: ``reset(position_mm)``, ``step(target_mm, dt_s, enabled)``,
``velocity_mm_s``, positions are drive readings = length - strut offset), use
the factory::

    from hexacnc.sim.strut import coupled_model_factory
    sim_drives(cfg, buses, model_factory=coupled_model_factory())   # hexacnc.sim.drives

The six per-strut views share one :class:`CoupledStruts`; it advances one step
once all six drives have a command for that step (commands queued per drive, so
bus threads that interleave never mix cycles); a drive ahead of the others reads
its newest command plus the model's current following error (one step old).
"""
from __future__ import annotations

import math

import numpy as np

from ..kinematics import Hexapod
from .dynamics import IFEXT, IQ, IQD, IWEXT, IY, NU, NX, CoupledModel, Gains, discretise_fast, \
    gains_from_bandwidth, tune_conventional

_TUNED: dict = {}


def default_gains(model: CoupledModel) -> Gains:
    """Configured gains, else the conventional tuning at the worst pose of a coarse grid (cached per config)."""
    cfg = model.cfg
    if cfg.dynamics.velocity_bandwidth_hz > 0:
        return gains_from_bandwidth(cfg, cfg.dynamics.velocity_bandwidth_hz)
    key = id(cfg)
    if key not in _TUNED:
        from .dynamics import eigen_grid, workspace_grid
        grid = workspace_grid(cfg, n_xyz=3)
        worst = np.asarray(eigen_grid(model, grid)["worst_pose"])
        _TUNED[key] = tune_conventional(model, worst)[0]
    return _TUNED[key]


class CoupledStruts:
    """Six struts + carrier, stepped along strut length commands (mm)."""

    def __init__(self, cfg, gains: Gains | None = None, update_s: float = 0.02):
        self.model = CoupledModel(cfg)
        self.hx: Hexapod = self.model.hx
        self.g = gains or default_gains(self.model)
        self.update_s = float(update_s)
        L = self.hx.lengths(cfg.home_pose)
        self.pose = np.asarray(cfg.home_pose, dtype=float).copy()
        self.reset(L)

    def reset(self, lengths_mm) -> None:
        """At rest at ``lengths_mm`` (6,)."""
        L = np.asarray(lengths_mm, dtype=float)
        self.r = L.copy()
        self.r1 = L.copy()
        self.r2 = L.copy()
        self.e = np.zeros(NX)
        self.position_mm = L.copy()
        self.length_mm = L.copy()
        self.velocity_mm_s = np.zeros(6)
        self._age = math.inf
        self._dt = None
        fk = self.hx.forward(L, self.pose)
        if fk.ok:
            self.pose = fk.pose

    def _refresh(self, dt: float) -> None:
        fk = self.hx.forward(self.r, self.pose)
        if fk.ok:
            self.pose = fk.pose
        J, R = self.model.jacobian(self.pose)
        A, B = self.model.matrices(J, R, self.g)
        self.Ad, self.Bd = discretise_fast(A, B, dt)
        self.J = J
        self.M = self.model.mass_matrix(R)
        self.Jinv = np.linalg.inv(J)
        self._age = 0.0
        self._dt = dt

    def step(self, cmd_mm, dt_s: float) -> np.ndarray:
        """Advance by ``dt_s`` with new commands (6,) mm; returns drive-side positions (6,) mm."""
        if dt_s <= 0:
            return self.position_mm
        self.r2, self.r1, self.r = self.r1, self.r, np.asarray(cmd_mm, dtype=float).copy()
        if self._dt != dt_s or self._age >= self.update_s:
            self._refresh(dt_s)
        self._age += dt_s
        acc = (self.r - 2 * self.r1 + self.r2) / (dt_s * dt_s)
        u = np.zeros(NU)
        u[IFEXT] = -self.model.md * acc
        u[IWEXT] = -self.M @ (self.Jinv @ acc)
        self.e = self.Ad @ self.e + self.Bd @ u
        rate = (self.r - self.r1) / dt_s
        self.position_mm = self.r + self.e[IQ]
        self.velocity_mm_s = rate + self.e[IQD]
        self.length_mm = self.r + self.J @ self.e[IY]
        return self.position_mm


class _StrutView:
    """One drive's view of a shared :class:`CoupledStruts` (simdrive ``StrutModel`` protocol)."""

    def __init__(self, shared: "_Shared", i: int):
        self.s = shared
        self.i = i

    @property
    def velocity_mm_s(self) -> float:
        return float(self.s.cs.velocity_mm_s[self.i]) if self.s.cs else 0.0

    @property
    def deflection_mm(self) -> float:
        """Dynamic elastic deflection of this strut (true length minus drive-side position), mm."""
        cs = self.s.cs
        return float(cs.length_mm[self.i] - cs.position_mm[self.i]) if cs else 0.0

    def reset(self, position_mm: float) -> None:
        self.s.reset(self.i, position_mm)

    def step(self, target_mm: float, dt_s: float, enabled: bool) -> float:
        return self.s.step(self.i, target_mm, dt_s, enabled)


class _Shared:
    """The coupled model behind six drive views, advanced once per cycle in step with all six.

    The drives are stepped from their buses' SYNC handlers, which may run on different threads
    and interleave (bus 0's SYNC k+1 before bus 1's SYNC k).  Each drive's commands are queued;
    the model advances by one step whenever every drive has a command for it, so all six commands
    of a step belong to the same cycle (no spurious acceleration from mixing cycles).  A drive that
    is ahead reads its newest command plus the model's current following error.  A drive that stops
    stepping (not operational) is held at its last command once another queue is ``MAX_LAG`` deep.
    """

    MAX_LAG = 8

    def __init__(self, cfg, gains=None):
        from collections import deque
        self.cs = CoupledStruts(cfg, gains)
        self.off = np.asarray(cfg.strut_offset_mm, dtype=float)
        self.q = [deque() for _ in range(6)]
        self.dt = None

    def reset(self, i: int, position_mm: float) -> None:
        L = self.cs.position_mm.copy()
        L[i] = position_mm + self.off[i]
        self.cs.reset(L)
        for q in self.q:
            q.clear()

    def _advance(self) -> None:
        cmd = self.cs.r.copy()
        for j, q in enumerate(self.q):
            if q:
                cmd[j] = q.popleft()
        self.cs.step(cmd, self.dt)

    def step(self, i: int, target_mm: float, dt_s: float, enabled: bool) -> float:
        self.dt = dt_s
        q = self.q
        q[i].append((target_mm + self.off[i]) if enabled else float(self.cs.position_mm[i]))
        while all(q) or max(len(x) for x in q) > self.MAX_LAG:
            self._advance()
        if not q[i]:
            return float(self.cs.position_mm[i] - self.off[i])
        # ahead of the others: the newest command plus the current following error
        return float(q[i][-1] + self.cs.e[IQ][i] - self.off[i])


def coupled_model_factory(gains: Gains | None = None):
    """A ``model_factory(strut, cfg)`` for ``drivers.simdrive.SimDrives``: six views of one coupled model."""
    state: dict = {}

    def factory(strut: int, cfg):
        if cfg is None:
            raise ValueError("the coupled strut model needs the machine configuration")
        sh = state.get(id(cfg))
        if sh is None:
            sh = state[id(cfg)] = _Shared(cfg, gains)
        return _StrutView(sh, strut)

    return factory
