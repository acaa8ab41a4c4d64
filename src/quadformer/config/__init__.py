"""Configuration of a simulated dataset: frozen dataclasses with SI units.

Every field is validated at construction; an invalid value raises ``ConfigError``
naming the field. ``SimConfig.from_dict`` builds a config from nested mappings (as read
from a TOML file at the CLI edge) and rejects unknown keys.

The vocabularies and the field checks are in ``config.base``, the sensors' configuration in
``config.sensors``; every name stays importable from ``quadformer.config``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields
from typing import Any, Mapping

from quadformer.config.base import (ATTACK_CHOICES, ATTACK_KINDS, KNOWLEDGE, MISSION_KINDS, MIX, MIX_KINDS,
                                    MIXABLE_KINDS, MODELS, NOISE_SHAPES, SENSOR_CONFIGS, SENSOR_NAMES, SHAPE_KINDS,
                                    STEALTH, ConfigError,
                                    _positive, _range, _require, parse_sensors)
from quadformer.config.sensors import BaroConfig, GPSConfig, IMUConfig, MagConfig, VIOConfig

__all__ = ["ATTACK_CHOICES", "ATTACK_KINDS", "HORIZONTAL_KINDS", "KIND_FIELDS", "KNOWLEDGE", "MISSION_KINDS", "MIX",
           "MIX_KINDS", "MIXABLE_KINDS", "MODELS", "STEALTH", "NOISE_SHAPES", "SENSOR_CONFIGS", "SENSOR_NAMES",
           "SHAPE_KINDS", "AttackConfig", "BaroConfig", "ConfigError", "EKFConfig", "GPSConfig", "IMUConfig",
           "MagConfig", "MissionConfig", "SimConfig", "VIOConfig", "merge", "parse_sensors", "unset_kind_fields"]


@dataclass(frozen=True)
class MissionConfig:
    kinds: tuple[str, ...] = MISSION_KINDS   # sampled uniformly per flight
    speed: tuple[float, float] = (1.0, 8.0)       # m/s, cruise speed range
    altitude: tuple[float, float] = (5.0, 30.0)   # m, altitude range
    max_accel: float = 3.0                        # m/s^2, bound used to size curves

    def __post_init__(self) -> None:
        kinds = tuple(self.kinds)
        _require(len(kinds) > 0, "mission.kinds", "must name at least one mission kind")
        for k in kinds:
            _require(k in MISSION_KINDS, "mission.kinds",
                     f"unknown mission kind {k!r}; choose from {', '.join(MISSION_KINDS)}")
        object.__setattr__(self, "kinds", kinds)
        object.__setattr__(self, "speed", _range("mission.speed", self.speed, lo=0.1))
        object.__setattr__(self, "altitude", _range("mission.altitude", self.altitude, lo=1.0))
        _positive("mission.max_accel", self.max_accel)


# Per-kind defaults of the attack distributions; None in AttackConfig means "use these".
_ATTACK_DEFAULTS: dict[str, dict[str, tuple[float, float]]] = {
    "bias": {"duration": (5.0, 20.0), "magnitude": (1.5, 6.0)},
    "ramp": {"duration": (10.0, 30.0), "rate": (0.2, 1.0)},
    "sinusoid": {"duration": (10.0, 30.0), "magnitude": (1.5, 6.0), "frequency": (0.05, 0.5)},
    "intermittent": {"duration": (10.0, 30.0), "magnitude": (1.5, 6.0), "period": (2.0, 6.0)},
    "replay": {"duration": (10.0, 30.0), "delay": (3.0, 10.0)},
    "freeze": {"duration": (5.0, 20.0)},
    "drift": {"duration": (10.0, 30.0), "rate": (0.2, 1.0), "accel": (0.05, 0.5)},
    "capture": {"duration": (10.0, 30.0), "magnitude": (5.0, 15.0), "rate": (0.5, 3.0), "capture_s": (2.0, 2.0),
                "lock_loss_s": (0.0, 0.6)},
    # a stealthy attacker's fix moves at most ``rate`` m/s from the truth (white box: as fast as the
    # detector lets it; black box: accelerating at ``accel``), from its onset to the flight's end
    STEALTH: {"duration": (1e6, 1e6), "rate": (3.0, 3.0), "accel": (0.05, 0.05)},
    "none": {},
}
_GENERIC = {"duration": (5.0, 20.0), "magnitude": (1.5, 6.0), "rate": (0.2, 1.0),
            "frequency": (0.05, 0.5), "period": (2.0, 6.0), "delay": (3.0, 10.0)}
#: the ranges only some kinds draw, and those kinds: left at None by a configuration none of whose
#: kinds draws them (so configurations made before they existed keep their cache keys)
KIND_FIELDS = {"accel": ("drift", STEALTH), "capture_s": ("capture",), "lock_loss_s": ("capture",)}
_KIND_GENERIC = {"accel": (0.05, 0.5), "capture_s": (2.0, 2.0), "lock_loss_s": (0.0, 0.6)}
#: kinds whose offset runs along a horizontal direction (their axes hold no z)
HORIZONTAL_KINDS = ("ramp", "drift", "capture", STEALTH)
#: the fields only a stealthy attack takes (None in every other configuration, and then left out of
#: its dict: ``unset_kind_fields``)
STEALTH_FIELDS = ("detector", "knowledge", "margin", "surrogate", "headings", "plan_accel")
#: the most headings a white or grey box searches at each GPS step
MAX_HEADINGS = 8


@dataclass(frozen=True)
class AttackConfig:
    """False data injection on GPS, y = g(x) + v + d. Ranges are sampled uniformly per flight.

    ``kind="mix"``: each attacked flight draws its kind uniformly from ``mix``, then its
    parameters from that kind's ranges: a range given here applies to every kind, one left
    at None takes each kind's own default (``ranges(kind)``). The ranges only drift and capture
    draw (``KIND_FIELDS``: accel, capture_s, lock_loss_s) stay None in a configuration none of
    whose kinds draws them."""
    kind: str = "none"                                 # one of ATTACK_KINDS, or "mix"
    fraction: float = 0.5                              # share of flights attacked (one window each)
    onset: tuple[float, float] = (10.0, 40.0)          # s
    duration: tuple[float, float] | None = None        # s (per-kind default)
    magnitude: tuple[float, float] | None = None       # m, offset norm (bias, sinusoid, intermittent, capture)
    rate: tuple[float, float] | None = None            # m/s, drift rate (ramp, drift, capture)
    frequency: tuple[float, float] | None = None       # Hz (sinusoid)
    period: tuple[float, float] | None = None          # s, on/off period (intermittent)
    delay: tuple[float, float] | None = None           # s, replay delay
    axes: str | None = None    # fixed attacked axes, e.g. "x" or "xz"; None: random sparse subset
    mix: tuple[str, ...] = MIX_KINDS                   # kinds a mixed attack draws from (kind "mix")
    accel: tuple[float, float] | None = None           # m/s^2, a drift's acceleration while it ramps in (drift)
    onset_step: bool | None = None     # drift: True the velocity steps to the rate at the onset, False it ramps
                                       # in at accel; None: drawn per flight (half the flights each)
    capture_s: tuple[float, float] | None = None       # s, a capture's pull-off time (capture)
    lock_loss_s: tuple[float, float] | None = None     # s, the fix lost at a capture's start (capture)
    detector: str | None = None        # stealthy: the detector it evades (a shipped name or a model file)
    knowledge: str | None = None       # stealthy: what it knows of it (``KNOWLEDGE``; default white)
    margin: float | None = None        # stealthy, white or grey box: the score kept under margin x threshold (0, 1]
    surrogate: str | None = None       # stealthy, grey box: the detector the attacker runs instead (the same
                                       # method fitted on its own flights: a model file or a shipped name)
    headings: int | None = None        # stealthy, white or grey box: the axes it searches each GPS step, evenly
                                       # spread from its direction (None: 1, along it only); with more, the
                                       # push that moves the fix farthest from the truth, in any of them
    plan_accel: float | None = None    # stealthy, white or grey box: its plan, m/s^2: the offset's speed grows at
                                       # most this much a second (the fastest push under the bound, at most the
                                       # plan's speed); None: no limit (the fastest push under the bound)

    def __post_init__(self) -> None:
        _require(self.kind in ATTACK_CHOICES, "attack.kind",
                 f"unknown attack {self.kind!r}; choose from {', '.join(ATTACK_CHOICES)}")
        _require(isinstance(self.fraction, (int, float)) and 0.0 <= self.fraction <= 1.0,
                 "attack.fraction", f"must be in [0, 1], got {self.fraction!r}")
        object.__setattr__(self, "onset", _range("attack.onset", self.onset, lo=0.0))
        mix = self.mix.split(",") if isinstance(self.mix, str) else self.mix
        _require(isinstance(mix, (tuple, list)) and len(mix) > 0, "attack.mix",
                 f"must name at least one attack kind, got {self.mix!r}")
        mix = tuple(str(k).strip() for k in mix)
        for k in mix:
            _require(k in MIXABLE_KINDS, "attack.mix",
                     f"unknown attack kind {k!r}; choose from {', '.join(MIXABLE_KINDS)}")
        _require(len(set(mix)) == len(mix), "attack.mix", f"a kind is named twice in {self.mix!r}")
        object.__setattr__(self, "mix", mix)
        defaults = _ATTACK_DEFAULTS.get(self.kind, {})
        for name, generic in _GENERIC.items():
            value = getattr(self, name)
            if value is None:
                if self.kind == MIX:
                    continue          # resolved per flight, from the kind it draws (ranges())
                value = defaults.get(name, generic)
            lo = 1e-6 if name in ("duration", "frequency", "period", "delay") else 0.0
            object.__setattr__(self, name, _range(f"attack.{name}", value, lo=lo))
        kinds = mix if self.kind == MIX else (self.kind,)
        for name, users in KIND_FIELDS.items():
            value = getattr(self, name)
            if value is None:
                if self.kind == MIX or self.kind not in users:
                    continue          # resolved per flight (ranges()), or drawn by no kind of this config
                value = defaults[name]
            value = _range(f"attack.{name}", value)
            if name == "lock_loss_s":
                _require(value[0] >= 0.0, f"attack.{name}", f"must be >= 0 s, got {getattr(self, name)!r}")
            else:
                _require(value[0] > 0.0, f"attack.{name}", f"must be > 0 ({'m/s^2' if name == 'accel' else 's'}), "
                         f"got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)
        self._check_stealth()
        _require(self.onset_step is None or isinstance(self.onset_step, bool), "attack.onset_step",
                 f"must be true, false or unset (drawn per flight), got {self.onset_step!r}")
        if "capture" in kinds:
            r = self.ranges("capture")
            _require(r["lock_loss_s"][1] <= r["capture_s"][0], "attack.lock_loss_s",
                     f"the fix must be back within the capture: the longest lock loss ({r['lock_loss_s'][1]} s) "
                     f"must not exceed the shortest capture (attack.capture_s {r['capture_s'][0]} s)")
        if self.axes is not None:
            axes = str(self.axes).lower()
            _require(len(axes) > 0 and set(axes) <= set("xyz") and len(set(axes)) == len(axes),
                     "attack.axes", f"must be a subset of 'xyz' such as 'x' or 'xy', got {self.axes!r}")
            _require(("x" in axes) or ("y" in axes), "attack.axes",
                     f"must include a horizontal axis (x or y), got {self.axes!r}")
            horizontal = [k for k in kinds if k in HORIZONTAL_KINDS]
            if horizontal:
                _require("z" not in axes, "attack.axes", f"a {horizontal[0]} drifts along a horizontal direction: "
                         "use x and/or y")
            object.__setattr__(self, "axes", axes)

    def _check_stealth(self) -> None:
        if self.kind != STEALTH:
            for name in STEALTH_FIELDS:
                _require(getattr(self, name) is None, f"attack.{name}",
                         f"only a stealthy attack takes it (attack.kind {self.kind!r})")
            return
        _require(isinstance(self.detector, str) and self.detector.strip() != "", "attack.detector",
                 "a stealthy attack needs the detector it evades: a shipped name (quadformer zoo list) or a "
                 "model file (quadformer fit)")
        knowledge = "white" if self.knowledge is None else self.knowledge
        _require(knowledge in KNOWLEDGE, "attack.knowledge",
                 f"unknown knowledge {self.knowledge!r}; choose from {', '.join(KNOWLEDGE)}")
        margin = 0.9 if self.margin is None else self.margin
        _require(isinstance(margin, (int, float)) and not isinstance(margin, bool) and 0.0 < margin <= 1.0,
                 "attack.margin", f"must be in (0, 1] (the share of the threshold the score is kept under), "
                 f"got {self.margin!r}")
        if knowledge == "grey":
            _require(isinstance(self.surrogate, str) and self.surrogate.strip() != "", "attack.surrogate",
                     "a grey-box attacker runs its own copy of the method: a model file of the same method "
                     "fitted on its own flights (quadformer fit), or a shipped detector of it")
        else:
            _require(self.surrogate is None, "attack.surrogate",
                     f"only a grey-box attacker runs a surrogate (attack.knowledge {knowledge!r})")
        if self.headings is not None:
            _require(isinstance(self.headings, int) and not isinstance(self.headings, bool)
                     and 1 <= self.headings <= MAX_HEADINGS, "attack.headings",
                     f"must be a whole number from 1 to {MAX_HEADINGS} (the axes searched), got {self.headings!r}")
            _require(knowledge != "black", "attack.headings",
                     "only a white or grey box searches headings (a black box has no score to search on)")
        if self.plan_accel is not None:
            _require(isinstance(self.plan_accel, (int, float)) and not isinstance(self.plan_accel, bool)
                     and math.isfinite(self.plan_accel) and self.plan_accel > 0, "attack.plan_accel",
                     f"must be a positive acceleration (m/s^2), got {self.plan_accel!r}")
            _require(knowledge != "black", "attack.plan_accel",
                     "only a white or grey box follows a plan under its score (a black box drifts at attack.accel)")
            _require((self.headings or 1) == 1, "attack.plan_accel",
                     "a plan runs along the attack's direction: with it, headings must be 1")
        object.__setattr__(self, "knowledge", knowledge)
        object.__setattr__(self, "margin", float(margin))

    @property
    def kinds(self) -> tuple[str, ...]:
        """The kinds the attacked flights may have: ``mix`` for a mixed attack, else ``(kind,)``
        (none for ``kind="none"``)."""
        if self.kind == MIX:
            return self.mix
        return () if self.kind == "none" else (self.kind,)

    def ranges(self, kind: str | None = None) -> dict[str, tuple[float, float]]:
        """The ranges a flight attacked by ``kind`` (default: the config's kind) draws from:
        the config's own where given, else that kind's defaults (``_ATTACK_DEFAULTS``)."""
        kind = self.kind if kind is None else kind
        _require(kind in (*ATTACK_KINDS, STEALTH), "attack.kind", f"ranges of a single kind, got {kind!r}")
        defaults = _ATTACK_DEFAULTS[kind]
        out = {}
        for name, generic in {**_GENERIC, **_KIND_GENERIC}.items():
            value = getattr(self, name)
            out[name] = value if value is not None else defaults.get(name, generic)
        return out


def unset_kind_fields(attack: dict[str, Any]) -> dict[str, Any]:
    """An ``AttackConfig`` as a dict (``dataclasses.asdict``) without the kind-specific fields it
    leaves unset (``KIND_FIELDS`` and ``onset_step`` at None), in place: what a configuration made
    before those fields existed holds, so hashes of it (cache keys) stay as they were."""
    for name in (*KIND_FIELDS, "onset_step", *STEALTH_FIELDS):
        if name in attack and attack[name] is None:
            attack.pop(name)
    return attack


@dataclass(frozen=True)
class EKFConfig:
    """Error-state EKF tuning. None: matched to the sensor configuration."""
    gps_pos_std_h: float | None = None    # m; default sqrt(white^2 + gauss_markov^2)
    gps_pos_std_v: float | None = None    # m
    gps_vel_std: float | None = None      # m/s
    vio_vel_std: float | None = None      # m/s
    vio_att_std_deg: float | None = None  # deg
    mag_heading_std_deg: float | None = None  # deg; default hypot(noise, bias) / field_h
    baro_std: float | None = None         # m; default sqrt(white^2 + gauss_markov^2)
    # Initial estimation error (the filter has converged on the ground before the mission).
    init_pos_std: float = 0.3             # m
    init_vel_std: float = 0.05            # m/s
    init_att_std_deg: float = 1.0         # deg

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if v is not None:
                _positive(f"ekf.{f.name}", v)


@dataclass(frozen=True)
class SimConfig:
    model: str = "I"                 # "I": hummingbird in calm air; "II": PX4 SIH quad in Dryden wind
    noise: str = "gaussian"          # GPS, VIO, magnetometer and barometer noise shape
    sensors: str = "gps+imu+vio"     # one of SENSOR_CONFIGS (any order of the names)
    attack: AttackConfig = field(default_factory=AttackConfig)
    flights: int = 8
    duration: float = 60.0           # s per flight
    seed: int = 0
    dt: float = 0.01                 # s, simulation, IMU and EKF propagation step (100 Hz)
    batch_size: int = 256            # flights simulated together (does not change the data)
    gps: GPSConfig = field(default_factory=GPSConfig)
    vio: VIOConfig = field(default_factory=VIOConfig)
    imu: IMUConfig = field(default_factory=IMUConfig)
    mission: MissionConfig = field(default_factory=MissionConfig)
    ekf: EKFConfig = field(default_factory=EKFConfig)
    mag: MagConfig = field(default_factory=MagConfig)
    baro: BaroConfig = field(default_factory=BaroConfig)

    def __post_init__(self) -> None:
        _require(self.model in MODELS, "model", f"unknown model {self.model!r}; choose from I, II")
        object.__setattr__(self, "sensors", parse_sensors(self.sensors))
        _require(self.noise in NOISE_SHAPES, "noise",
                 f"unknown noise shape {self.noise!r}; choose from {', '.join(NOISE_SHAPES)}")
        _require(isinstance(self.flights, int) and not isinstance(self.flights, bool) and self.flights >= 1,
                 "flights", f"must be an integer >= 1, got {self.flights!r}")
        _positive("duration", self.duration)
        _positive("dt", self.dt)
        _require(isinstance(self.seed, int) and self.seed >= 0, "seed", f"must be a non-negative integer, got {self.seed!r}")
        _require(isinstance(self.batch_size, int) and self.batch_size >= 1, "batch_size",
                 f"must be an integer >= 1, got {self.batch_size!r}")
        for name, rate in (("gps.rate_hz", self.gps.rate_hz), ("vio.rate_hz", self.vio.rate_hz),
                           ("mag.rate_hz", self.mag.rate_hz), ("baro.rate_hz", self.baro.rate_hz)):
            ratio = 1.0 / (rate * self.dt)
            _require(abs(ratio - round(ratio)) < 1e-9 and round(ratio) >= 1, name,
                     f"the sensor period must be a whole number of simulation steps (dt={self.dt} s)")
        _require(self.steps_per_gps * self.n_gps == self.n_steps, "duration",
                 f"must be a whole number of GPS periods ({1.0 / self.gps.rate_hz} s), got {self.duration}")
        if self.attack.kind != "none":
            _require(self.attack.onset[1] < self.duration, "attack.onset",
                     f"the latest onset ({self.attack.onset[1]} s) must be before the end of the flight "
                     f"(duration {self.duration} s)")

    def has(self, sensor: str) -> bool:
        """Whether the configuration includes ``sensor`` (one of ``SENSOR_NAMES``)."""
        _require(sensor in SENSOR_NAMES, "sensor", f"unknown sensor {sensor!r}; choose from {', '.join(SENSOR_NAMES)}")
        return sensor in self.sensors.split("+")

    # Derived step counts.
    @property
    def n_steps(self) -> int:
        return int(round(self.duration / self.dt))

    @property
    def steps_per_gps(self) -> int:
        return int(round(1.0 / (self.gps.rate_hz * self.dt)))

    @property
    def steps_per_vio(self) -> int:
        return int(round(1.0 / (self.vio.rate_hz * self.dt)))

    @property
    def steps_per_mag(self) -> int:
        return int(round(1.0 / (self.mag.rate_hz * self.dt)))

    @property
    def steps_per_baro(self) -> int:
        return int(round(1.0 / (self.baro.rate_hz * self.dt)))

    @property
    def n_gps(self) -> int:
        return int(round(self.duration * self.gps.rate_hz))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "SimConfig":
        return _build(cls, data, prefix="")

    def replace(self, **changes: Any) -> "SimConfig":
        return dataclasses.replace(self, **changes)


def _build(cls: type, data: Mapping[str, Any], prefix: str) -> Any:
    if not isinstance(data, Mapping):
        raise ConfigError(f"{prefix.rstrip('.') or 'config'}: expected a table, got {data!r}")
    known = {f.name: f for f in fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if key not in known:
            raise ConfigError(f"{prefix}{key}: unknown setting; known: {', '.join(sorted(known))}")
        sub = _NESTED.get((cls.__name__, key))
        if sub is not None:
            kwargs[key] = _build(sub, value, prefix=f"{prefix}{key}.")
        elif isinstance(value, list):
            kwargs[key] = tuple(value)
        else:
            kwargs[key] = value
    return cls(**kwargs)


_NESTED: dict[tuple[str, str], type] = {
    ("SimConfig", "attack"): AttackConfig,
    ("SimConfig", "gps"): GPSConfig,
    ("SimConfig", "vio"): VIOConfig,
    ("SimConfig", "imu"): IMUConfig,
    ("SimConfig", "mission"): MissionConfig,
    ("SimConfig", "ekf"): EKFConfig,
    ("SimConfig", "mag"): MagConfig,
    ("SimConfig", "baro"): BaroConfig,
}


def merge(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """Deep-merge two nested mappings (override wins)."""
    out = dict(base)
    for k, v in override.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = merge(out[k], v)
        else:
            out[k] = v
    return out
