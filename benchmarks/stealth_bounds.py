"""The stealth benchmark's physical bound of a shipped set under other sensors: what bounds it.

``experiments.stealth_envelope.physical_bound`` propagates the filter's GPS-free position uncertainty from
its start, with the configuration the set's detectors were trained on. This prints it for the
set as shipped and with the parts that bound it changed one at a time: the filter's starting
tilt uncertainty (``ekf.init_att_std_deg``), and an IMU with a datasheet's noise and bias instead
of the fleet's vibration-level noise measured over GPS intervals:

    python benchmarks/stealth_bounds.py                 # magbaro
    python benchmarks/stealth_bounds.py --set vio
"""

from __future__ import annotations

import argparse
import copy

#: an IMU as a datasheet states it (a MEMS part without the airframe's vibration): accelerometer
#: and gyro noise densities (m/s^2/sqrt(Hz), rad/s/sqrt(Hz)), turn-on accelerometer bias std (m/s^2)
DATASHEET = {"accel_noise_density": 0.004, "gyro_noise_density": 0.0015, "accel_bias_std": 0.005}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", default="magbaro", help="a shipped set (its default detector's training simulation)")
    ap.add_argument("--horizons", default="10,30,60,120", help="s after the onset")
    args = ap.parse_args()

    from quadformer.config import SimConfig
    from quadformer.detectors import pretrained
    from quadformer.experiments.stealth_envelope import physical_bound

    shipped = pretrained.sets()
    if args.set not in shipped:
        ap.error(f"--set {args.set!r}: choose from {', '.join(shipped)}")
    name = shipped[args.set].default
    base = copy.deepcopy(pretrained.load(name).calibration_["sim_config"])
    horizons = tuple(float(h) for h in args.horizons.split(","))
    cases = [("as shipped", {}, None), ("tilt known to 0.1 deg", {}, 0.1),
             ("datasheet IMU", DATASHEET, None), ("datasheet IMU, tilt known to 0.1 deg", DATASHEET, 0.1)]
    print(f"{args.set} ({name}): IMU {base['imu']}, starting tilt std {base['ekf']['init_att_std_deg']} deg")
    for label, imu, tilt in cases:
        sim = copy.deepcopy(base)
        sim["imu"].update(imu)
        if tilt is not None:
            sim["ekf"]["init_att_std_deg"] = tilt
        bound = physical_bound(SimConfig.from_dict(sim), horizons)
        print(f"  {label:40s} " + ", ".join(f"{k} s: {v:.1f} m" for k, v in bound.items()))


if __name__ == "__main__":
    main()
