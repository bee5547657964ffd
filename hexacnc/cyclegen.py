"""Unrolled hot path for :class:`hexacnc.transform.CycleTransform`.

At start-up the machine's constants (joint positions, axes, limits, the LU
pivot order at the home pose) are folded into straight-line Python source,
compiled once, and bound to the transform.  Everything per cycle then lives in
local variables: no loops, no containers, no attribute chains.  Zero constants
(joints in the z = 0 plane, say) drop their terms.

If a pivot of the fixed-order LU becomes small (far from home, near a
singularity) the generated code hands the cycle to the general routine with
partial pivoting, so the result never depends on the pivot order.
"""
from __future__ import annotations

import math

import numpy as np

from .cyclecodes import CODES
from .pose import ROTATION_STATEMENTS


def _lin(terms: list[tuple[str, float]]) -> str:
    """``c1*v1 + c2*v2 ...`` with zero constants dropped and unit constants simplified."""
    out = []
    for var, c in terms:
        if c == 0.0:
            continue
        if c == 1.0:
            out.append(f"+{var}")
        elif c == -1.0:
            out.append(f"-{var}")
        else:
            out.append(f"+{var}*{c!r}")
    if not out:
        return "0.0"
    s = "".join(out)
    return s[1:] if s.startswith("+") else s


def static_pivot_order(J: np.ndarray) -> list[int]:
    """Row order of partial pivoting on ``J`` (perm[k] = original row at position k)."""
    A = np.array(J, dtype=float)
    perm = list(range(6))
    for k in range(6):
        p = k + int(np.argmax(np.abs(A[k:, k])))
        if p != k:
            A[[k, p]] = A[[p, k]]
            perm[k], perm[p] = perm[p], perm[k]
        A[k + 1:, k:] -= np.outer(A[k + 1:, k] / A[k, k], A[k, k:])
    return perm


def generate_source(ct) -> str:
    """Source of ``command(self, x, y, z, a, b, c)`` and ``feedback(self, lengths)``."""
    hx = ct.hx
    Jt = hx.jacobian_twist_rad(hx.home_rad)
    Jt[:, 3:] /= hx.char_length_mm
    perm = static_pivot_order(Jt)
    L: list[str] = []
    w = L.append
    names = _lu_names()
    _emit_ik(ct, w, perm)
    _emit_lu(ct, w, names)
    _emit_sag(ct, w, perm)
    _emit_guard(ct, w)
    w("")
    _emit_feedback(ct, w, perm, names)
    return "\n".join(L) + "\n"


def _lu_names() -> list[str]:
    """Names of the LU factors the command stores for the feedback (L below, U on/above the diagonal)."""
    return [f"m{r}{k}" for k in range(6) for r in range(k + 1, 6)] + \
           [f"a{k}{cc}" for k in range(6) for cc in range(k, 6)]


def _emit_rotation(w, indent: str) -> None:
    for stmt in ROTATION_STATEMENTS:
        w(indent + stmt)


def _emit_ik(ct, w, perm: list[int]) -> None:
    """Input check, rotation, spindle growth, strut lengths, joint cones and the Jacobian rows."""
    pos = [perm.index(i) for i in range(6)]
    sc = ct._scale
    w("def command(self, x, y, z, a, b, c):")
    w("    if not (x - x == 0.0 and y - y == 0.0 and z - z == 0.0 and a - a == 0.0 and b - b == 0.0 and c - c == 0.0):")
    w("        return LIMIT_INPUT")
    w("    ca = cos(a); sa = sin(a); cb = cos(b); sb = sin(b); cc = cos(c); sc = sin(c)")
    _emit_rotation(w, "    ")
    w("    pc = self.pose_cmd; pc[0] = x; pc[1] = y; pc[2] = z; pc[3] = a; pc[4] = b; pc[5] = c")
    ax, ay, az = ct._axis
    w("    g = self.spindle_growth_mm")
    w("    if g != 0.0:")
    w(f"        x -= g * ({_lin([('r00', ax), ('r01', ay), ('r02', az)])})")
    w(f"        y -= g * ({_lin([('r10', ax), ('r11', ay), ('r12', az)])})")
    w(f"        z -= g * ({_lin([('r20', ax), ('r21', ay), ('r22', az)])})")
    w("    Lm = self.length_mm")
    for i in range(6):
        px, py, pz = ct._p[i]
        bx, by, bz = ct._b[i]
        ex, ey, ez = ct._ab[i]
        qx, qy, qz = ct._ap[i]
        k = pos[i]
        w(f"    # strut {i + 1} (LU row {k})")
        w(f"    rx = {_lin([('r00', px), ('r01', py), ('r02', pz)])}")
        w(f"    ry = {_lin([('r10', px), ('r11', py), ('r12', pz)])}")
        w(f"    rz = {_lin([('r20', px), ('r21', py), ('r22', pz)])}")
        w(f"    sx = x + rx - {bx!r}; sy = y + ry - {by!r}; sz = z + rz - {bz!r}")
        w("    li = sqrt(sx * sx + sy * sy + sz * sz)")
        w(f"    Lm[{i}] = li")
        w(f"    if li < {ct._lmin[i]!r} or li > {ct._lmax[i]!r}:")
        w(f"        self.fail_index = {i}; self.fail_value = li; return LIMIT_LENGTH")
        w("    ux = sx / li; uy = sy / li; uz = sz / li")
        w(f"    cj = {_lin([('ux', ex), ('uy', ey), ('uz', ez)])}")
        w(f"    if cj < {ct._cos_max[i]!r}:")
        w(f"        self.fail_index = {i}; self.fail_value = cj; return LIMIT_JOINT")
        wx = _lin([('r00', qx), ('r01', qy), ('r02', qz)])
        wy = _lin([('r10', qx), ('r11', qy), ('r12', qz)])
        wz = _lin([('r20', qx), ('r21', qy), ('r22', qz)])
        w(f"    cj = -(ux * ({wx}) + uy * ({wy}) + uz * ({wz}))")
        w(f"    if cj < {ct._cos_max[i]!r}:")
        w(f"        self.fail_index = {i + 6}; self.fail_value = cj; return LIMIT_JOINT")
        w(f"    a{k}0 = ux; a{k}1 = uy; a{k}2 = uz")
        w(f"    a{k}3 = (ry * uz - rz * uy) * {sc!r}; a{k}4 = (rz * ux - rx * uz) * {sc!r}; "
          f"a{k}5 = (rx * uy - ry * ux) * {sc!r}")


def _emit_lu(ct, w, names: list[str]) -> None:
    """LU factorisation with the static pivot order; a small pivot hands over to the general routine."""
    minp = ct._min_pivot
    w("    # LU factorisation, fixed pivot order; small pivot -> general routine")
    for k in range(6):
        w(f"    if -{minp!r} < a{k}{k} < {minp!r}:")
        w("        return self._command_generic(pc[0], pc[1], pc[2], a, b, c)")
        if k < 5:
            w(f"    iv = 1.0 / a{k}{k}")
        for r in range(k + 1, 6):
            w(f"    m{r}{k} = a{r}{k} * iv")
            if k + 1 < 6:
                w("    " + "; ".join(f"a{r}{cc} -= m{r}{k} * a{k}{cc}" for cc in range(k + 1, 6)))
    w("    F = self._lu_fast")
    w("    " + "; ".join(f"F[{j}] = {n}" for j, n in enumerate(names)))
    w("    self._factored = True; self._fast = True")


def _emit_sag(ct, w, perm: list[int]) -> None:
    """Strut forces from the carrier's weight (J^T f = wrench, with the stored LU) and the sag."""
    sc = ct._scale
    w("    sag = self.sag_mm")
    w("    if self.sag_enabled:")
    Fx, Fy, Fz = ct._F
    cx, cy, cz = ct._cog
    w(f"        gx = {_lin([('r00', cx), ('r01', cy), ('r02', cz)])}")
    w(f"        gy = {_lin([('r10', cx), ('r11', cy), ('r12', cz)])}")
    w(f"        gz = {_lin([('r20', cx), ('r21', cy), ('r22', cz)])}")
    # wrench (rotation rows scaled like J's columns)
    w(f"        w0 = {Fx!r}; w1 = {Fy!r}; w2 = {Fz!r}")
    w(f"        w3 = (gy * {Fz!r} - gz * {Fy!r}) * {sc!r}")
    w(f"        w4 = (gz * {Fx!r} - gx * {Fz!r}) * {sc!r}")
    w(f"        w5 = (gx * {Fy!r} - gy * {Fx!r}) * {sc!r}")
    for i in range(6):          # U^T z = w
        terms = " ".join(f"- a{j}{i} * z{j}" for j in range(i))
        w(f"        z{i} = (w{i} {terms}) / a{i}{i}")
    for i in range(5, -1, -1):  # L^T y = z
        terms = " ".join(f"- m{j}{i} * y{j}" for j in range(i + 1, 6))
        w(f"        y{i} = z{i} {terms}")
    w("        f = self.force_N")
    for k in range(6):
        w(f"        f[{perm[k]}] = y{k}; sag[{perm[k]}] = y{k} * {ct._inv_k[perm[k]]!r}")


def _emit_guard(ct, w) -> None:
    """Commands (length - sag - thermal, calibrated map) and the velocity/acceleration guard."""
    w("    th = self.thermal_mm; cmd = self.cmd_mm; p1 = self._prev; p2 = self._prev2")
    for i in range(6):
        w(f"    v{i} = Lm[{i}] - sag[{i}] - th[{i}]")
    if ct.calibrated:
        _emit_calibrated_command(ct, w)
    w("    if self._have_prev >= 2:")
    for i in range(6):
        w(f"        d1 = v{i} - p1[{i}]")
        w(f"        if d1 > {ct._dl_max[i]!r} or d1 < -{ct._dl_max[i]!r}:")
        w(f"            self.fail_index = {i}; self.fail_value = d1 / {ct.dt!r}; return LIMIT_VELOCITY")
        w(f"        d2 = d1 - p1[{i}] + p2[{i}]")
        w(f"        if d2 > {ct._ddl_max[i]!r} or d2 < -{ct._ddl_max[i]!r}:")
        w(f"            self.fail_index = {i}; self.fail_value = d2 / {ct.dt * ct.dt!r}; return LIMIT_ACCELERATION")
    w("    else:")
    w("        self._have_prev += 1")
    for i in range(6):
        w(f"    p2[{i}] = p1[{i}]; p1[{i}] = v{i}; cmd[{i}] = v{i}")
    w("    return OK")


def _emit_feedback(ct, w, perm: list[int], names: list[str]) -> None:
    """Forward kinematics: Newton steps with the command's stored LU, from an extrapolated guess."""
    w("def feedback(self, lengths):")
    w("    if not self._fast:")
    w("        return self._feedback_generic(lengths)")
    w("    sag = self.sag_mm; th = self.thermal_mm")
    for i in range(6):
        if ct.calibrated:
            _emit_calibrated_feedback(ct, w, i)
        else:
            w(f"    t{i} = lengths[{i}] + sag[{i}] + th[{i}]")
    w("    X = self.pose_act; last = self._last; h1 = self._h1; h2 = self._h2")
    w("    n = self._nhist")
    w("    if n >= 3:")
    for j in range(6):
        w(f"        X{j} = 3.0 * last[{j}] - 3.0 * h1[{j}] + h2[{j}]")
    w("    elif n == 2:")
    for j in range(6):
        w(f"        X{j} = 2.0 * last[{j}] - h1[{j}]")
    w("    else:")
    w("        " + "; ".join(f"X{j} = last[{j}]" for j in range(6)))
    w("    F = self._lu_fast")
    w("    " + "; ".join(f"{n} = F[{j}]" for j, n in enumerate(names)))
    w(f"    tol = {ct._tol!r}")
    w("    it = 0")
    w("    while True:")
    w("        ca = cos(X3); sa = sin(X3); cb = cos(X4); sb = sin(X4); cc = cos(X5); sc = sin(X5)")
    _emit_rotation(w, "        ")
    _emit_fk_step(ct, w, perm)
    w("    self.fk_iterations = it; self.fk_residual_mm = res")
    w("    if not res <= tol:")
    w("        " + "; ".join(f"X[{j}] = last[{j}]" for j in range(6)))
    w("        self._nhist = 1")
    w("        return FK_NOT_CONVERGED")
    w("    " + "; ".join(f"h2[{j}] = h1[{j}]; h1[{j}] = last[{j}]; last[{j}] = X{j}; X[{j}] = X{j}"
                         for j in range(6)))
    w("    if n < 3:")
    w("        self._nhist = n + 1")
    w("    return OK")


def _emit_fk_step(ct, w, perm: list[int]) -> None:
    """One Newton step of the forward kinematics (inside the loop): residuals, solve, pose update."""
    sc = ct._scale
    for i in range(6):
        px, py, pz = ct._p[i]
        bx, by, bz = ct._b[i]
        w(f"        sx = X0 + {_lin([('r00', px), ('r01', py), ('r02', pz)])} - {bx!r}")
        w(f"        sy = X1 + {_lin([('r10', px), ('r11', py), ('r12', pz)])} - {by!r}")
        w(f"        sz = X2 + {_lin([('r20', px), ('r21', py), ('r22', pz)])} - {bz!r}")
        w(f"        e{i} = t{i} - sqrt(sx * sx + sy * sy + sz * sz)")
    w("        res = max(abs(e0), abs(e1), abs(e2), abs(e3), abs(e4), abs(e5))")
    w(f"        if res <= tol or it >= {ct._max_iter} or res != res:")
    w("            break")
    for i in range(6):          # forward with L on the permuted rhs
        terms = " ".join(f"- m{i}{j} * q{j}" for j in range(i))
        w(f"        q{i} = e{perm[i]} {terms}")
    for i in range(5, -1, -1):
        terms = " ".join(f"- a{i}{j} * d{j}" for j in range(i + 1, 6))
        w(f"        d{i} = (q{i} {terms}) / a{i}{i}")
    w(f"        ox = d3 * {sc!r}; oy = d4 * {sc!r}; oz = d5 * {sc!r}")
    w("        da = (cc * ox + sc * oy) / cb")
    w("        X0 += d0; X1 += d1; X2 += d2; X3 += da; X4 += cc * oy - sc * ox; X5 += oz + sb * da")
    w("        it += 1")


def _horner(coeffs, var: str) -> str:
    """``((c_n*v + c_n-1)*v + ...) + c_0`` with the constants folded in as literals."""
    cs = [float(c) for c in coeffs]
    expr = repr(cs[-1])
    for c in reversed(cs[:-1]):
        expr = f"({expr}) * {var}" + (f" + {c!r}" if c != 0.0 else "")
    return expr


def _emit_calibrated_command(ct, w) -> None:
    """Physical lengths v0..v5 -> drive-scale commands (calibrated map, :mod:`hexacnc.strutmap`).

    Linear maps fold to ``v * m + c``; polynomial maps take one Newton step in t from a
    warm-start guess and hand the rare case whose step is not below the map's tolerance
    to :meth:`StrutMap.solve_t` (more steps).
    The commands are then checked against the stroke.
    """
    sm = ct.strut_map
    w("    ph = self.phys_mm; cs = self._cal_state")
    for i in range(6):
        A = [float(v) for v in sm.A[i]]
        o = float(sm.offset[i]); c = float(sm.center[i]); h = float(sm.half[i])
        w(f"    ph[{i}] = v{i}")
        if len(A) == 2:
            # o + c + h * (v - o - A0) / A1
            m = h / A[1]
            k = o + c - m * (o + A[0])
            w(f"    v{i} = v{i} * {m!r} + {k!r}")
        else:
            B = [float(v) for v in sm.B[i]]
            tol = float(sm.step_tol_t[i])
            j = 2 * i
            A0 = [A[0] + o] + A[1:]          # G(t) + strut_offset: compared with v directly
            w(f"    t = cs[{j}] + v{i} * cs[{j + 1}]")
            w(f"    gp = {_horner(B, 't')}")
            w("    if gp > 0.0:")
            w(f"        dt = (v{i} - ({_horner(A0, 't')})) / gp")
            w("        t += dt")
            w("    else:")
            w("        dt = 1.0")
            w(f"    if not -{tol!r} < dt < {tol!r}:")          # NaN too
            w(f"        t, gp = self.strut_map.solve_t({i}, v{i}, t)")
            w("        if t != t:")
            w(f"            cs[{j}] = {-(o + A[0]) / A[1]!r}; cs[{j + 1}] = {1.0 / A[1]!r}")
            w(f"            self.fail_index = {i}; self.fail_value = v{i}; return LIMIT_CALIBRATION")
            w("    g = 1.0 / gp")
            w(f"    cs[{j}] = t - v{i} * g; cs[{j + 1}] = g")
            w(f"    v{i} = t * {h!r} + {o + c!r}")
        w(f"    if not {ct._lmin[i]!r} <= v{i} <= {ct._lmax[i]!r}:")   # NaN never reaches a drive
        w(f"        self.fail_index = {i + 6}; self.fail_value = v{i}; return LIMIT_LENGTH")


def _emit_calibrated_feedback(ct, w, i: int) -> None:
    """t_i = calibrated physical length of drive-scale length ``lengths[i]`` + sag + thermal."""
    sm = ct.strut_map
    A = [float(v) for v in sm.A[i]]
    o = float(sm.offset[i]); c = float(sm.center[i]); ih = 1.0 / float(sm.half[i])
    w(f"    u = lengths[{i}] * {ih!r} - {(o + c) * ih!r}")
    w(f"    t{i} = ({_horner([A[0] + o] + A[1:], 'u')}) + sag[{i}] + th[{i}]")


def bind_fast_path(ct) -> str:
    """Compile the generated source and bind ``command``/``feedback`` to ``ct``; returns the source."""
    src = generate_source(ct)
    ns: dict = {"cos": math.cos, "sin": math.sin, "sqrt": math.sqrt, **CODES}
    exec(compile(src, f"<hexacnc cycle {ct.cfg.name}>", "exec"), ns)
    ct._lu_fast = [0.0] * 36
    ct.command = ns["command"].__get__(ct)
    ct.feedback = ns["feedback"].__get__(ct)
    return src
