"""The error-state EKF's equations for one flight at a time, compiled (numba), looped over flights.

The same equations as ``estimator.eskf`` (its docstring states the states and conventions) and
the GPS-free reference's propagation (``estimator.reference``), on preallocated float64 arrays
updated in place: p, v (n,3), q (n,4) xyzw, ba, bg (n,3), P (n,15,15); the reference's state
x (n,3,3) (axis, [position, velocity, acceleration error]) and covariance C (n,3,3,3). Every
update takes a dense H (n,m,15); a selection H gives the torch path's numbers to rounding
(multiplying by 0 and 1 is exact). Small-angle quaternion maps use the same series as
``geometry.so3``; larger angles and the heading use ``math.atan2`` (the torch path's own atan2
agrees to about 1e-15 rad).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

GRAVITY_Z = -9.81
SMALL = 0.1   # rad, below which the series of geometry.so3 are used

jit = njit(cache=True, fastmath=False, nogil=True)


@jit
def rotmat(q, R):
    """Rotation matrix R (3,3) of the unit quaternion q (4,) xyzw (body to world)."""
    x, y, z, w = q[0], q[1], q[2], q[3]
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - z * w)
    R[0, 2] = 2 * (x * z + y * w)
    R[1, 0] = 2 * (x * y + z * w)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - x * w)
    R[2, 0] = 2 * (x * z - y * w)
    R[2, 1] = 2 * (y * z + x * w)
    R[2, 2] = 1 - 2 * (x * x + y * y)


@jit
def exp_quat(px, py, pz, out):
    """Rotation vector to unit quaternion (xyzw) in out (4,)."""
    th2 = px * px + py * py + pz * pz
    if th2 < SMALL * SMALL:
        x2 = th2 / 4.0
        sinc = 1 - x2 / 6 * (1 - x2 / 20 * (1 - x2 / 42 * (1 - x2 / 72)))
        cos = 1 - x2 / 2 * (1 - x2 / 12 * (1 - x2 / 30 * (1 - x2 / 56 * (1 - x2 / 90))))
    else:
        th = math.sqrt(th2)
        sinc = 2 * math.sin(th / 2) / th
        cos = math.cos(th / 2)
    out[0] = px / 2 * sinc
    out[1] = py / 2 * sinc
    out[2] = pz / 2 * sinc
    out[3] = cos


@jit
def log_quat(q, out):
    """Unit quaternion (4,) xyzw to rotation vector out (3,), angle in [0, pi]."""
    sign = -1.0 if q[3] < 0 else 1.0
    vx, vy, vz, w = sign * q[0], sign * q[1], sign * q[2], sign * q[3]
    s2 = vx * vx + vy * vy + vz * vz
    if s2 < (SMALL / 2) ** 2:
        k = 2 * (1 + s2 * (1 / 6 + s2 * (3 / 40 + s2 * (5 / 112 + s2 * (35 / 1152 + s2 * 63 / 2816)))))
    else:
        s = math.sqrt(s2)
        k = 2 * math.atan2(s, w) / s
    out[0] = vx * k
    out[1] = vy * k
    out[2] = vz * k


@jit
def quat_mul(a, b, out):
    """Hamilton product a * b of xyzw quaternions into out (out may not alias a or b)."""
    ax, ay, az, aw = a[0], a[1], a[2], a[3]
    bx, by, bz, bw = b[0], b[1], b[2], b[3]
    out[0] = aw * bx + ax * bw + ay * bz - az * by
    out[1] = aw * by - ax * bz + ay * bw + az * bx
    out[2] = aw * bz + ax * by - ay * bx + az * bw
    out[3] = aw * bw - ax * bx - ay * by - az * bz


@jit
def rotate_by(q, dphi0, dphi1, dphi2):
    """q <- normalise(q * Exp(dphi)), in place."""
    e = np.empty(4)
    out = np.empty(4)
    exp_quat(dphi0, dphi1, dphi2, e)
    quat_mul(q, e, out)
    norm = math.sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2] + out[3] * out[3])
    for i in range(4):
        q[i] = out[i] / norm


@jit
def sandwich(F, P, tmp):
    """P <- F P F^T in place (square matrices of one size), ``tmp`` a scratch matrix of it."""
    n = P.shape[0]
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += F[i, k] * P[k, j]
            tmp[i, j] = s
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += tmp[i, k] * F[j, k]
            P[i, j] = s


@jit
def imu_step(p, v, q, ba, bg, P, rx, rC, imu, dt, qdiag, accel_std, q_b):
    """One IMU sample imu (n,6) (specific force, body rate; FLU) over dt seconds: the reference
    (``rx``, ``rC``) propagated through the state before its own propagation, then the
    filter's predict with the process noise ``qdiag`` (12,) of error states 3..14."""
    n = p.shape[0]
    R = np.empty((3, 3))
    F = np.empty((15, 15))
    FP = np.empty((15, 15))
    Rf = np.empty((3, 3))
    Fr = np.empty((3, 3))
    tmp3 = np.empty((3, 3))
    e = np.empty(4)
    Re = np.empty((3, 3))
    a = np.empty(3)
    # the reference's transition per axis: (position, velocity, acceleration error)
    Fr[0, 0], Fr[0, 1], Fr[0, 2] = 1.0, dt, -0.5 * dt * dt
    Fr[1, 0], Fr[1, 1], Fr[1, 2] = 0.0, 1.0, -dt
    Fr[2, 0], Fr[2, 1], Fr[2, 2] = 0.0, 0.0, 1.0
    for b in range(n):
        rotmat(q[b], R)
        f0, f1, f2 = imu[b, 0] - ba[b, 0], imu[b, 1] - ba[b, 1], imu[b, 2] - ba[b, 2]
        w0, w1, w2 = imu[b, 3] - bg[b, 0], imu[b, 4] - bg[b, 1], imu[b, 5] - bg[b, 2]
        for i in range(3):
            a[i] = R[i, 0] * f0 + R[i, 1] * f1 + R[i, 2] * f2
        a[2] += GRAVITY_Z
        for ax in range(3):                  # the reference, through the state before its propagation
            acc = a[ax] - rx[b, ax, 2]
            x0, x1 = rx[b, ax, 0], rx[b, ax, 1]
            rx[b, ax, 0] = x0 + x1 * dt + 0.5 * acc * dt * dt
            rx[b, ax, 1] = x1 + acc * dt
            C = rC[b, ax]
            sandwich(Fr, C, tmp3)
            C[1, 1] += (accel_std * dt) ** 2
            C[2, 2] += q_b[ax]
        # nominal state
        for i in range(3):
            p[b, i] = p[b, i] + v[b, i] * dt + 0.5 * a[i] * dt * dt
            v[b, i] = v[b, i] + a[i] * dt
        # error-state transition (before the attitude moves: R and f, w of the old state)
        for i in range(15):
            for j in range(15):
                F[i, j] = 1.0 if i == j else 0.0
        # Rf = -R skew(f)
        for i in range(3):
            Rf[i, 0] = -(R[i, 1] * f2 - R[i, 2] * f1)
            Rf[i, 1] = -(R[i, 2] * f0 - R[i, 0] * f2)
            Rf[i, 2] = -(R[i, 0] * f1 - R[i, 1] * f0)
        h2 = 0.5 * dt * dt
        for i in range(3):
            F[i, 3 + i] = dt
            for j in range(3):
                F[i, 6 + j] = Rf[i, j] * h2
                F[i, 9 + j] = -R[i, j] * h2
                F[3 + i, 6 + j] = Rf[i, j] * dt
                F[3 + i, 9 + j] = -R[i, j] * dt
        exp_quat(-w0 * dt, -w1 * dt, -w2 * dt, e)
        rotmat(e, Re)
        wx, wy, wz = w0 * dt, w1 * dt, w2 * dt
        for i in range(3):
            for j in range(3):
                F[6 + i, 6 + j] = Re[i, j]
        # -(I - 0.5 skew(w dt)) dt
        F[6, 12], F[6, 13], F[6, 14] = -dt, -(0.5 * wz) * dt, -(-0.5 * wy) * dt
        F[7, 12], F[7, 13], F[7, 14] = -(-0.5 * wz) * dt, -dt, -(0.5 * wx) * dt
        F[8, 12], F[8, 13], F[8, 14] = -(0.5 * wy) * dt, -(-0.5 * wx) * dt, -dt
        rotate_by(q[b], w0 * dt, w1 * dt, w2 * dt)
        Pb = P[b]
        sandwich(F, Pb, FP)
        for d in range(12):
            Pb[3 + d, 3 + d] += qdiag[d]


@jit
def update(p, v, q, ba, bg, P, H, r, var, w_out, nis_out, s_out, dx_out):
    """Kalman update of every flight with innovation r (n,m) = H dx + noise, H (n,m,15), noise
    variances var (n,m). Writes the whitened innovation L^-1 r (S = L L^T), the NIS, sqrt(diag
    S) and the correction dx (n,15); the covariance in Joseph form, both symmetrised as in
    ``eskf.update``."""
    n, m = r.shape
    PHt = np.empty((15, m))
    S = np.empty((m, m))
    L = np.zeros((m, m))
    Kt = np.empty((m, 15))
    A = np.empty((15, 15))
    AP = np.empty((15, 15))
    Pn = np.empty((15, 15))
    y = np.empty(m)
    for b in range(n):
        for i in range(m):
            if not math.isfinite(r[b, i]):
                raise ValueError("non-finite innovation")
        Pb = P[b]
        Hb = H[b]
        for i in range(15):
            for j in range(m):
                s = 0.0
                for k in range(15):
                    s += Pb[i, k] * Hb[j, k]
                PHt[i, j] = s
        for i in range(m):
            for j in range(m):
                s = 0.0
                for k in range(15):
                    s += Hb[i, k] * PHt[k, j]
                S[i, j] = s
            S[i, i] += var[b, i]
        for i in range(m):
            for j in range(i):
                a = 0.5 * (S[i, j] + S[j, i])
                S[i, j] = a
                S[j, i] = a
        # Cholesky S = L L^T
        for i in range(m):
            for j in range(i + 1):
                s = S[i, j]
                for k in range(j):
                    s -= L[i, k] * L[j, k]
                if i == j:
                    if not s > 0.0:         # also NaN: a non-finite sample or state
                        raise ValueError("innovation covariance not positive definite")
                    L[i, i] = math.sqrt(s)
                else:
                    L[i, j] = s / L[j, j]
        nis = 0.0
        for i in range(m):
            s = r[b, i]
            for k in range(i):
                s -= L[i, k] * w_out[b, k]
            w_out[b, i] = s / L[i, i]
            nis += w_out[b, i] * w_out[b, i]
            s_out[b, i] = math.sqrt(S[i, i])
        nis_out[b] = nis
        # Kt = S^-1 (P H^T)^T: forward then backward substitution, column by column
        for c in range(15):
            for i in range(m):
                s = PHt[c, i]
                for k in range(i):
                    s -= L[i, k] * y[k]
                y[i] = s / L[i, i]
            for i in range(m - 1, -1, -1):
                s = y[i]
                for k in range(i + 1, m):
                    s -= L[k, i] * Kt[k, c]
                Kt[i, c] = s / L[i, i]
        for i in range(15):
            s = 0.0
            for j in range(m):
                s += Kt[j, i] * r[b, j]
            dx_out[b, i] = s
        # A = I - K H
        for i in range(15):
            for j in range(15):
                s = 0.0
                for k in range(m):
                    s += Kt[k, i] * Hb[k, j]
                A[i, j] = (1.0 if i == j else 0.0) - s
        sandwich(A, Pb, AP)
        for i in range(15):
            for j in range(15):
                t = 0.0
                for k in range(m):
                    t += Kt[k, i] * var[b, k] * Kt[k, j]
                Pn[i, j] = Pb[i, j] + t
        for i in range(15):
            for j in range(15):
                Pb[i, j] = 0.5 * (Pn[i, j] + Pn[j, i])
        for i in range(3):
            p[b, i] += dx_out[b, i]
            v[b, i] += dx_out[b, 3 + i]
            ba[b, i] += dx_out[b, 9 + i]
            bg[b, i] += dx_out[b, 12 + i]
        rotate_by(q[b], dx_out[b, 6], dx_out[b, 7], dx_out[b, 8])


@jit
def vio_innovation(v, q, meas, r):
    """VIO innovation (n,6): measured minus estimated velocity, and the attitude error
    Log(q^-1 q_meas), from meas (n,7) velocity and attitude (xyzw)."""
    n = v.shape[0]
    conj = np.empty(4)
    d = np.empty(4)
    th = np.empty(3)
    for b in range(n):
        for i in range(3):
            r[b, i] = meas[b, i] - v[b, i]
        conj[0], conj[1], conj[2], conj[3] = -q[b, 0], -q[b, 1], -q[b, 2], q[b, 3]
        quat_mul(conj, meas[b, 3:7], d)
        log_quat(d, th)
        for i in range(3):
            r[b, 3 + i] = th[i]


@jit
def mag_heading(q, mag, field, r, H):
    """Heading innovation r (n,1) of the body-frame field mag (n,3) against the Earth field
    (3,) (world, ENU) and its H (n,1,15): ``eskf.mag_heading``'s equations."""
    n = q.shape[0]
    R = np.empty((3, 3))
    fx, fy, fz = field[0], field[1], field[2]
    for b in range(n):
        rotmat(q[b], R)
        m0 = R[0, 0] * mag[b, 0] + R[0, 1] * mag[b, 1] + R[0, 2] * mag[b, 2]
        m1 = R[1, 0] * mag[b, 0] + R[1, 1] * mag[b, 1] + R[1, 2] * mag[b, 2]
        cross = m0 * fy - m1 * fx
        dot = m0 * fx + m1 * fy
        a = math.atan2(cross, dot) if (cross != 0.0 or dot != 0.0) else 0.0
        if a >= math.pi:
            a -= 2 * math.pi
        r[b, 0] = a
        for k in range(15):
            H[b, 0, k] = 0.0
        c = fz / (fx * fx + fy * fy)
        for j in range(3):
            H[b, 0, 6 + j] = R[2, j] - c * (fx * R[0, j] + fy * R[1, j])


@jit
def scalar_updates(x, C, first, j, r, var):
    """The reference's Kalman update of state component j on the axes first, first + 1, ...
    of r (n,k), noise variances var (k,): ``reference._scalar_update``."""
    n, k = r.shape
    for b in range(n):
        for a in range(k):
            ax = first + a
            Cs = C[b, ax]
            s = Cs[j, j] + var[a]
            col = np.empty(3)
            for i in range(3):
                col[i] = Cs[i, j]
            for i in range(3):
                K = col[i] / s
                x[b, ax, i] += K * r[b, a]
                for l in range(3):
                    Cs[i, l] -= K * col[l]
            for i in range(3):
                for l in range(i):
                    a = 0.5 * (Cs[i, l] + Cs[l, i])
                    Cs[i, l] = a
                    Cs[l, i] = a
