"""The vocabularies of a configuration (models, noise shapes, attack and mission kinds, sensors)
and the checks every configuration's fields go through (``ConfigError`` naming the field)."""

from __future__ import annotations

import math
from typing import Any

MODELS = ("I", "II")
NOISE_SHAPES = ("gaussian", "exponential", "laplace")
#: the attack shapes the shape typer fits and alerts are typed as (``estimator.schema.ATTACK_TYPES``)
SHAPE_KINDS = ("bias", "ramp", "sinusoid", "intermittent", "replay", "freeze")
#: every attack kind: the shapes, and two a real spoofer makes: ``drift`` (a consistent drift switched
#: on at once or accelerating in) and ``capture`` (an SDR capture: a pull-off with the receiver's
#: signature, then a drift)
ATTACK_KINDS = ("none", *SHAPE_KINDS, "drift", "capture")
#: a mixed attack: each attacked flight draws its own kind from ``AttackConfig.mix``
MIX = "mix"
#: the kinds a mixed attack may draw (every kind but "none")
MIXABLE_KINDS = tuple(k for k in ATTACK_KINDS if k != "none")
#: the default of ``AttackConfig.mix``: the shapes (drift and capture only where named, so the
#: default mixed datasets draw what they drew before those kinds existed)
MIX_KINDS = SHAPE_KINDS
#: an attacker who knows the detector: each fix chosen as it flies (``attacks.stealthy``), not a
#: shape drawn beforehand; never mixed with the others
STEALTH = "stealthy"
#: what a stealthy attacker knows: ``white`` runs the detector's own stream on the fixes it is about
#: to send and keeps its score under ``margin`` x threshold; ``black`` sees no score and moves the fix
#: as a slow accelerating drift (``accel``, up to ``rate``)
KNOWLEDGE = ("white", "grey", "black")
#: the values of ``AttackConfig.kind``
ATTACK_CHOICES = (*ATTACK_KINDS, MIX, STEALTH)
MISSION_KINDS = ("hover", "circle", "lissajous", "minsnap")
#: sensors a configuration may name, in the canonical order of ``SimConfig.sensors``
SENSOR_NAMES = ("gps", "imu", "vio", "mag", "baro")
#: supported sensor configurations (canonical form)
SENSOR_CONFIGS = ("gps+imu+vio", "gps+imu+mag+baro", "gps+imu+vio+mag+baro")


class ConfigError(ValueError):
    """An invalid configuration value; the message names the field."""


def _require(cond: bool, name: str, msg: str) -> None:
    if not cond:
        raise ConfigError(f"{name}: {msg}")


def _positive(name: str, value: float) -> None:
    _require(isinstance(value, (int, float)) and math.isfinite(value) and value > 0,
             name, f"must be a positive finite number, got {value!r}")


def _non_negative(name: str, value: float) -> None:
    _require(isinstance(value, (int, float)) and math.isfinite(value) and value >= 0,
             name, f"must be a non-negative finite number, got {value!r}")


def parse_sensors(text: Any, name: str = "sensors") -> str:
    """The canonical form of a sensor configuration such as ``"imu+gps+mag+baro"``: names
    joined by ``+`` in the order of ``SENSOR_NAMES``; ``ConfigError`` unless supported."""
    choices = ", ".join(SENSOR_CONFIGS)
    _require(isinstance(text, str), name, f"must be a string such as 'gps+imu+vio', got {text!r}; "
             f"choose from {choices}")
    parts = [p.strip().lower() for p in text.split("+")]
    unknown = [p for p in parts if p not in SENSOR_NAMES]
    _require(not unknown, name, f"unknown sensor {', '.join(map(repr, unknown))} in {text!r}; "
             f"choose from {choices}")
    _require(len(set(parts)) == len(parts), name, f"a sensor is named twice in {text!r}; choose from {choices}")
    canonical = "+".join(n for n in SENSOR_NAMES if n in parts)
    _require(canonical in SENSOR_CONFIGS, name, f"unsupported sensor configuration {text!r}; choose from {choices}")
    return canonical


def _range(name: str, value: Any, lo: float = -math.inf) -> tuple[float, float]:
    _require(isinstance(value, (tuple, list)) and len(value) == 2, name,
             f"must be a pair (low, high), got {value!r}")
    a, b = (float(v) for v in value)
    _require(math.isfinite(a) and math.isfinite(b) and a <= b, name,
             f"must satisfy low <= high with finite values, got {value!r}")
    _require(a >= lo, name, f"values must be >= {lo}, got {value!r}")
    return (a, b)
