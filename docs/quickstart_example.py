# Quick start: simulate a few flights, split them by flight, fit, calibrate and detect.
# The six lines below are the README's; tests/test_api.py runs them.
from quadformer import AttackConfig, SimConfig, make, simulate, split_flights
attack = AttackConfig(kind="bias", onset=(6.0, 10.0), duration=(6.0, 10.0))   # GPS offset on half the flights
ds = simulate(SimConfig(model="II", noise="laplace", flights=6, duration=24.0, seed=3, attack=attack))
parts = split_flights(ds.scenarios, seed=0).frames(ds.flights)   # train / validation / test flights
det = make("cusum").fit(parts.train).calibrate(parts.val)       # threshold chosen on validation flights
print(parts.test.assign(alarm=det.predict(parts.test)).groupby("flight_id")[["label", "alarm"]].mean())
