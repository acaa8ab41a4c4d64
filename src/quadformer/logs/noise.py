"""Sensor noise estimated from clean flight logs, as simulator settings.

A detector trained in simulation expects the residue statistics of the simulated sensors; a
fleet whose GPS or IMU is quieter or noisier than the simulator's defaults shifts them. This
estimates, from logs without spoofing, the noise levels the simulator models, so that
``quadformer simulate --noise-from LOG`` produces data of the fleet's noise (and the replay
matched to that simulation has the filter tuning the data call for):

- GPS position: the fixes against the autopilot's own estimate (which fuses them with the IMU).
  Its variance beyond the white part is slow, Gauss-Markov-like error; the white part is the
  receiver's own (below) where the logs allow, else the step-to-step part of that difference
  (std of first differences / sqrt 2), which carries the estimate's jitter too.
- IMU and GPS velocity, as the filter meets them (``interval_noise``): over each GPS interval in
  the air, the receiver's velocity change minus the IMU's (its specific force through the
  autopilot's attitude, integrated over the interval the receiver's latency earlier): what a
  consistent drift's velocity step is judged against. On the shared real logs that spread is 0.04
  to 0.3 m/s per 0.2 s interval, nearly all of it the IMU's (0.14 to 0.86 m/s^2/sqrt(Hz); the
  raw samples' spread pooled, 0.37), where the fixes against the autopilot's estimate read the
  receiver's velocity noise as 0.35 m/s: that estimate's own jitter. White velocity noise of the
  receiver enters two neighbouring intervals' residuals with opposite signs, so it is the negative
  of their covariance; the rest of one interval's spread is the IMU's, as a density over the
  interval; the receiver's white position noise comes from its own consistency the same way. The
  IMU's is pooled over the logs' intervals; the receiver's is the largest of the logs' (each a
  lower bound, and a filter tuned below a receiver's noise doubles it in its innovations). Where
  a log lacks the attitude or enough intervals in the air: the IMU's sample-to-sample spread
  (vibration counted as noise) and the GPS against the autopilot's estimate; ``accel_from`` says
  which.
- Barometer: its altitude against the autopilot's height, white and slow parts as for GPS.
- Magnetometer: the step-to-step part of the field.

Estimates below a floor (a simulator's sensor is never perfect) are raised to it. Every
estimate pools the samples of all logs given.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from quadformer.logs.flightlog import FlightLog, LogError

FLOORS = {"gps_pos_h": 0.05, "gps_pos_v": 0.05, "gps_vel": 0.02, "gps_gm": 0.0, "accel_density": 1e-3,
          "gyro_density": 1e-4, "baro_noise": 0.05, "baro_gm": 0.0, "mag_noise": 5e-4}


@dataclass(frozen=True)
class NoiseEstimate:
    gps_pos_h: float      # m, white horizontal position noise
    gps_pos_v: float      # m, white vertical position noise
    gps_vel: float        # m/s, white velocity noise
    gps_gm: float         # m, slow (Gauss-Markov) position error
    accel_density: float  # m/s^2/sqrt(Hz)
    gyro_density: float   # rad/s/sqrt(Hz)
    baro_noise: float     # m
    baro_gm: float        # m
    mag_noise: float      # gauss
    logs: int
    gps_fixes: int
    #: where the IMU and GPS velocity noise come from: "gps intervals" (``interval_noise``, every
    #: log), "imu samples" (no log allows it), or "mixed" (pooled from both kinds of log)
    accel_from: str = "imu samples"
    intervals: int = 0    # GPS intervals in the air the interval estimate rests on

    def sim_overrides(self) -> dict[str, Any]:
        """Nested ``SimConfig`` settings (``SimConfig.from_dict`` / ``--set`` keys)."""
        return {"gps": {"pos_std_h": self.gps_pos_h, "pos_std_v": self.gps_pos_v, "vel_std": self.gps_vel,
                        "gm_std": self.gps_gm},
                "imu": {"accel_noise_density": self.accel_density, "gyro_noise_density": self.gyro_density},
                "baro": {"noise_std": self.baro_noise, "gm_std": self.baro_gm},
                "mag": {"noise_std": self.mag_noise}}

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _white_and_slow(d: np.ndarray) -> tuple[float, float]:
    """(white std, slow std) of differences d (n, k) pooled over columns: the white part from
    first differences, the slow part from the variance left over."""
    d = d[np.isfinite(d).all(axis=1)]
    if len(d) < 3:
        return float("nan"), float("nan")
    white = float(np.sqrt(np.mean(np.diff(d, axis=0) ** 2) / 2))
    total = float(np.mean((d - d.mean(axis=0)) ** 2))
    return white, float(np.sqrt(max(total - white ** 2, 0.0)))


def _interp(t: np.ndarray, ref, cols) -> np.ndarray:
    return np.stack([np.interp(t, ref["t"].to_numpy(), ref[c].to_numpy()) for c in cols], axis=1)


@dataclass(frozen=True)
class IntervalNoise:
    """The IMU and GPS velocity noise of one log as the filter meets them (``interval_noise``)."""
    accel_density: float     # m/s^2/sqrt(Hz): the IMU's share of one interval's velocity residual
    gps_vel: float           # m/s: the receiver's white velocity noise, per axis
    gps_pos_h: float         # m: the receiver's white horizontal position noise, per axis
    spread: float            # m/s: robust std of one interval's velocity residual, per axis
    interval_s: float        # s: the receiver's interval
    intervals: int           # intervals in the air it rests on
    latency_s: float         # s: the receiver's latency the IMU's interval was shifted by


def interval_noise(log: FlightLog, air: np.ndarray | None = None) -> IntervalNoise | None:
    """The IMU and GPS velocity noise of ``log`` from its GPS intervals in the air (``air``: a flag
    per fix; default the log's flight phase). The residual e_k of each interval (the receiver's
    horizontal velocity change minus the IMU's, ``receiver_clock.velocity_steps`` at the latency
    the log shows) is IMU noise integrated over the interval plus the difference of two fixes'
    velocity noise, which makes neighbouring residuals' covariance the negative of the receiver's
    velocity variance:

        gps_vel^2 = max(0, -cov(e_k, e_k+1))
        accel_density^2 = 2 (var(e) - 2 gps_vel^2) / interval

    (the simulator's density: a sample's std is the density x sqrt(rate / 2), so white noise
    integrated over T seconds spreads density x sqrt(T / 2)), robustly: 1.4826 MAD for the
    spreads, the covariance from the spreads of e_k + e_k+1 and e_k - e_k+1. The receiver's white
    position noise likewise, from its own consistency c_k (position change minus the mean velocity
    times the interval): gps_pos_h^2 = max(0, -cov(c_k, c_k+1)). None without GPS, IMU and
    attitude, or with fewer than 30 intervals.

    Slow errors (an IMU tilt or bias drifting over seconds, a receiver's smoothing) make the
    covariances positive and hide white noise below them: the receiver's shares are lower bounds,
    the IMU's an upper one, and one interval's spread is kept either way. On the shared real logs
    the receivers' consistency residuals are 0.6 to 0.9 correlated from one interval to the next,
    and no white part shows (0 m, where the fixes against the autopilot's estimate read 0.16 m:
    that estimate's own jitter)."""
    from quadformer.estimator.latency import robust_std
    from quadformer.logs.receiver_clock import latency_steps
    from quadformer.logs.replay import in_air

    if log.gps is None or len(log.gps) < 10:
        return None
    t = log.gps["t"].to_numpy(dtype=float)
    air = in_air(log, t) > 0.5 if air is None else np.asarray(air, bool)
    delay, e = latency_steps(log, air, every=True)
    if e is None:
        return None
    step = float(np.median(np.diff(t)))
    ok = np.isfinite(e).all(axis=1)
    steps = e[ok]
    var = robust_std(steps) ** 2
    gv2 = max(0.0, -_neighbour_cov(e, ok))
    q2 = 2.0 * max(0.0, var - 2.0 * gv2) / step
    c = _consistency(log.gps)
    gp2 = max(0.0, -_neighbour_cov(c, ok & np.isfinite(c).all(axis=1)))
    return IntervalNoise(float(np.sqrt(q2)), float(np.sqrt(gv2)), float(np.sqrt(gp2)), float(np.sqrt(var)), step,
                         len(steps), float(delay or 0.0))


def _consistency(g) -> np.ndarray:
    """The receiver's horizontal consistency over each interval of its fixes ``g`` (fixes - 1, 2):
    its position change minus the mean of the two velocities times the interval."""
    t = g["t"].to_numpy(dtype=float)
    p, v = g[["x", "y"]].to_numpy(dtype=float), g[["vx", "vy"]].to_numpy(dtype=float)
    return np.diff(p, axis=0) - 0.5 * (v[1:] + v[:-1]) * np.diff(t)[:, None]


def _neighbour_cov(e: np.ndarray, ok: np.ndarray) -> float:
    """Robust covariance of neighbouring rows of ``e`` (per axis, pooled) where both are ``ok``:
    a quarter of the difference of the squared robust stds of their sum and their difference;
    0 with fewer than 30 pairs."""
    from quadformer.estimator.latency import robust_std

    pair = ok[1:] & ok[:-1]
    a, b = e[:-1][pair], e[1:][pair]
    if len(a) < 30:
        return 0.0
    return (robust_std(a + b) ** 2 - robust_std(a - b) ** 2) / 4.0


def estimate_noise(logs: list[FlightLog]) -> NoiseEstimate:
    """Noise levels pooled over ``logs`` (clean flights), floored at ``FLOORS``."""
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("h", "v", "vel", "acc", "gyro", "baro", "mag")}
    rates: list[float] = []
    fixes = 0
    for log in logs:
        g, e = log.gps, log.estimate
        if g is not None and e is not None and len(g) > 3 and len(e) > 1:
            d = g[["x", "y", "z"]].to_numpy() - _interp(g["t"].to_numpy(), e, ["x", "y", "z"])
            parts["h"].append(d[:, :2])
            parts["v"].append(d[:, 2:])
            dv = g[["vx", "vy", "vz"]].to_numpy() - _interp(g["t"].to_numpy(), e, ["vx", "vy", "vz"])
            parts["vel"].append(dv)
            fixes += len(g)
        if log.imu is not None and len(log.imu) > 3:
            imu = log.imu
            rates.append(1.0 / float(np.median(np.diff(imu["t"].to_numpy()))))
            parts["acc"].append(imu[["ax", "ay", "az"]].to_numpy())
            parts["gyro"].append(imu[["gx", "gy", "gz"]].to_numpy())
        if log.baro is not None and e is not None and len(log.baro) > 3:
            b = log.baro
            z = _interp(b["t"].to_numpy(), e, ["z"])[:, 0]
            parts["baro"].append((b["alt"].to_numpy() - z)[:, None])
        if log.mag is not None and len(log.mag) > 3:
            parts["mag"].append(log.mag[["mx", "my", "mz"]].to_numpy())
    if not fixes:
        raise LogError("noise: no log with both GPS fixes and the autopilot's position estimate; the GPS noise "
                       "cannot be estimated")

    def pooled(key: str) -> tuple[float, float]:
        """White and slow std pooled over logs (variances weighted by samples)."""
        ests = [(len(d), *_white_and_slow(d)) for d in parts[key] if len(d) >= 3]
        ests = [e for e in ests if np.isfinite(e[1])]
        if not ests:
            return float("nan"), float("nan")
        n = np.array([e[0] for e in ests], float)
        w = np.sqrt(np.sum(n * np.array([e[1] for e in ests]) ** 2) / n.sum())
        s = np.sqrt(np.sum(n * np.array([e[2] for e in ests]) ** 2) / n.sum())
        return float(w), float(s)

    h_w, h_s = pooled("h")
    v_w, _ = pooled("v")
    vel_w, _ = pooled("vel")
    acc_w, _ = pooled("acc")
    gyro_w, _ = pooled("gyro")
    baro_w, baro_s = pooled("baro")
    mag_w, _ = pooled("mag")
    rate = float(np.median(rates)) if rates else 100.0
    density = np.sqrt(rate / 2.0)              # per-sample std = density * sqrt(rate / 2)
    raw = {"gps_pos_h": h_w, "gps_pos_v": v_w, "gps_vel": vel_w, "gps_gm": h_s, "accel_density": acc_w / density,
           "gyro_density": gyro_w / density, "baro_noise": baro_w, "baro_gm": baro_s, "mag_noise": mag_w}
    # the IMU and the receiver as the filter meets them, where the logs allow (the IMU's variance
    # pooled over the intervals, the receiver's the largest); a log without them counts with its raw
    # estimates (its samples' spread, its fixes against the autopilot's estimate)
    found = [(lg, interval_noise(lg)) for lg in logs]
    got = [f for _, f in found if f is not None]
    source = "imu samples"
    n = 0
    if got:
        n = sum(f.intervals for f in got)
        raw_acc, raw_vel = raw["accel_density"], raw["gps_vel"]
        raw_pos = raw["gps_pos_h"]
        acc2 = sum(f.intervals * f.accel_density ** 2 for f in got) / n
        # the receivers' white noise is each log's lower bound (slow errors hide it), and a filter
        # tuned below a receiver's own noise doubles it in its innovations (a fix's velocity
        # zig-zagging by 0.4 m/s reads as steps of 0.8): the largest of the logs', not their pool
        vel2 = max(f.gps_vel for f in got) ** 2
        pos2 = max(f.gps_pos_h for f in got) ** 2
        rest = [lg for lg, f in found if f is None and lg.gps is not None]
        m = sum(len(lg.gps) for lg in rest)      # the others' raw figures (the IMU's weighted a fix an interval)
        if m and np.isfinite(raw_acc):
            acc2 = (n * acc2 + m * raw_acc ** 2) / (n + m)
            vel2 = max(vel2, raw_vel ** 2) if np.isfinite(raw_vel) else vel2
            pos2 = max(pos2, raw_pos ** 2) if np.isfinite(raw_pos) else pos2
        source = "mixed" if m else "gps intervals"
        raw.update(accel_density=float(np.sqrt(acc2)), gps_vel=float(np.sqrt(vel2)), gps_pos_h=float(np.sqrt(pos2)))
    out = {k: max(FLOORS[k], v) if np.isfinite(v) else FLOORS[k] for k, v in raw.items()}
    return NoiseEstimate(**{k: float(v) for k, v in out.items()}, logs=len(logs), gps_fixes=fixes,
                         accel_from=source, intervals=n)


# --------------------------------------------------------------------------- detectability
#: the chance a spoof at the floor is detected (the floor's definition)
FLOOR_PROBABILITY = 0.9


@dataclass(frozen=True)
class DetectionFloor:
    """The smallest horizontal GPS offset and consistent drift a test on one GPS interval can
    tell from a log's own noise at a false-alarm budget (see ``detection_floor``)."""
    offset_m: float          # m: a position step of this size is seen with FLOOR_PROBABILITY
    drift_ms: float          # m/s: a velocity step (a drift switched on at once) likewise
    sigma_pos_m: float       # m: robust std of the GPS position change minus the GPS velocity's, per axis
    sigma_vel_ms: float      # m/s: robust std of the GPS velocity change minus the IMU's, per axis
    gps_rate_hz: float
    intervals: int           # GPS intervals in the air the estimate rests on
    per_hour: float          # the false-alarm budget (per in-air hour)
    # the same floors with the log's own tails: a Student-t of ``tail_dof_*`` degrees of freedom
    # fitted to the residuals (NaN where the fit fails); a Gaussian's (dof infinite) are the above
    offset_tail_m: float = float("nan")
    drift_tail_ms: float = float("nan")
    tail_dof_pos: float = float("nan")
    tail_dof_vel: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _step_floor(sigma: float, per_hour: float, rate_hz: float, prob: float = FLOOR_PROBABILITY) -> float:
    """The horizontal step (2 axes, direction unknown) that a chi-square test of one interval's
    2-d residual of per-axis std ``sigma`` detects with probability ``prob`` at ``per_hour`` false
    alarms per hour of tests at ``rate_hz``."""
    from scipy import optimize, stats

    alpha = per_hour / (3600.0 * rate_hz)
    gate = float(stats.chi2.isf(alpha, 2))
    f = lambda s: float(stats.ncx2.sf(gate, 2, (s / sigma) ** 2)) - prob   # noqa: E731
    return float(optimize.brentq(f, 1e-9 * sigma, 100.0 * sigma))


#: the fewest degrees of freedom a tail fit may give: below, the variance is infinite and a floor
#: from a few hundred intervals meaningless (the fit's dof is raised to it)
TAIL_MIN_DOF = 2.5
#: the most: above, a Student-t is a Gaussian for this purpose and the Gaussian's floor is given
TAIL_MAX_DOF = 100.0


def tail_floor(z: np.ndarray, per_hour: float, rate_hz: float,
               prob: float = FLOOR_PROBABILITY) -> tuple[float, float]:
    """(floor in units of the robust std, degrees of freedom) of one interval's 2-d residual ``z``
    (n, 2; already divided by its robust std) with its own tails: a bivariate Student-t (a Gaussian
    whose variance is scaled by one chi-square draw per interval, shared by both axes) whose scale
    and degrees of freedom nu are fitted by maximum likelihood to the pooled axes. Its test
    statistic |z|^2 / (2 scale^2) is F(2, nu) distributed, which sets the gate at the budget's
    per-interval chance; the step seen with probability ``prob`` is then found by integrating the
    non-central chi-square over the variance's draw. A fit above ``TAIL_MAX_DOF`` (Gaussian tails)
    gives the Gaussian's floor of the fitted scale and dof infinite; NaN where the fit fails."""
    from scipy import integrate, optimize, stats

    x = np.asarray(z, dtype=float)
    x = x[np.isfinite(x).all(axis=1)]
    if len(x) < 30:
        return float("nan"), float("nan")
    nu, _, scale = stats.t.fit(x.ravel(), floc=0.0)
    if not (np.isfinite(nu) and np.isfinite(scale) and scale > 0):
        return float("nan"), float("nan")
    nu = max(float(nu), TAIL_MIN_DOF)
    if nu >= TAIL_MAX_DOF:
        return _step_floor(float(scale), per_hour, rate_hz, prob), float("inf")
    alpha = per_hour / (3600.0 * rate_hz)
    gate = 2.0 * float(stats.f.isf(alpha, 2, nu))    # on |z / scale|^2
    w = stats.gamma(nu / 2.0, scale=2.0 / nu)        # the variance's draw: chi2(nu) / nu

    def seen(step: float) -> float:
        f = lambda u: float(stats.ncx2.sf(gate * u, 2, (step / scale) ** 2 * u)) * float(w.pdf(u))  # noqa: E731
        return float(integrate.quad(f, 0.0, np.inf, limit=200)[0]) - prob

    try:
        return float(optimize.brentq(seen, 1e-6, 1e4) * scale), nu
    except ValueError:
        return float("nan"), nu


def detection_floor(log: FlightLog, in_air: np.ndarray | None = None, per_hour: float = 1.0) -> DetectionFloor | None:
    """The physical floor of ``log``: the smallest offset and drift detectable at ``per_hour`` false
    alarms per in-air hour given the log's own GPS and IMU noise, with FLOOR_PROBABILITY.

    Over each GPS interval in the air (``in_air``: a flag per GPS fix; default every fix), the
    receiver's position change minus its mean velocity times the interval (a position step
    without the velocity: an offset), and its velocity change minus the IMU's specific force
    rotated to the world by the autopilot's attitude and integrated over the interval, gravity
    removed (a velocity step the IMU did not feel: a drift switched on at once), the IMU's interval
    taken the receiver's latency earlier (``receiver_clock.latency``: the one that makes that
    residual the least spread). Their robust
    per-axis std (1.4826 MAD) and a chi-square test of one interval's horizontal pair, Gaussian
    with that std, at the budget's per-interval false-alarm chance, give the floors. Heavier
    tails than a Gaussian's raise the true floor. A test over several intervals goes below it only
    where one interval's velocity residual is correlated with the next's; on the shared real logs
    it is not (lag-one autocorrelation -0.11 to 0.27), so for a velocity step the one-interval
    test is as sharp as the log allows.

    Real residuals have heavier tails than a Gaussian of their robust std: on the shared clean
    logs the largest of one flight's few hundred to 1500 intervals is 5 to 9 robust stds, where a
    Gaussian's would be 3.5 to 4. ``offset_tail_m`` and ``drift_tail_ms`` are the floors with the
    log's own tails (``tail_floor``: a Student-t fitted to the residuals), which a detector with
    no false alarm at the budget cannot go below either; they extrapolate the fitted tail to the
    budget's per-interval chance, far beyond the log's own count of intervals, and are as good as
    that fit. None without GPS, IMU and the autopilot's attitude."""
    from quadformer.estimator.latency import robust_std
    from quadformer.logs.receiver_clock import latency_steps

    g = log.gps
    if g is None or len(g) < 10:
        return None
    t = g["t"].to_numpy(dtype=float)
    p = g[["x", "y"]].to_numpy(dtype=float)
    v = g[["vx", "vy"]].to_numpy(dtype=float)
    air = np.ones(len(t), bool) if in_air is None else np.asarray(in_air, bool)
    _, e = latency_steps(log, air)
    if e is None:
        return None
    dt = np.diff(t)
    step = float(np.median(dt))
    ok = (air[1:] & air[:-1] & (dt > 0) & (dt <= 1.5 * step) & np.isfinite(p).all(axis=1)[1:]
          & np.isfinite(p).all(axis=1)[:-1] & np.isfinite(v).all(axis=1)[1:] & np.isfinite(v).all(axis=1)[:-1])
    c = _consistency(g)[ok]
    sp = robust_std(c)
    rate = 1.0 / step
    sv = robust_std(e)
    pos_tail, pos_dof = tail_floor(c / sp, per_hour, rate) if sp > 0 else (float("nan"), float("nan"))
    vel_tail, vel_dof = tail_floor(e / sv, per_hour, rate) if sv > 0 else (float("nan"), float("nan"))
    return DetectionFloor(_step_floor(sp, per_hour, rate), _step_floor(sv, per_hour, rate), sp, sv, rate,
                          int(ok.sum()), per_hour, pos_tail * sp, vel_tail * sv, pos_dof, vel_dof)
