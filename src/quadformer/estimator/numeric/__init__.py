"""The filter for flights whose arithmetic runs compiled (numba): a recorded log or a live
vehicle, one flight (or a few replayed together) at microseconds per IMU sample.

- ``kernels``: the error-state EKF's propagation and updates and the reference's propagation,
  compiled, looped over flights, in place on preallocated arrays;
- ``reference``: the GPS-free reference's comparisons and anchor on numpy arrays;
- ``filter``: ``NumericFilter``, ``OnlineFilter``'s twin (numpy in, numpy rows out).

The torch filter (``estimator.eskf``, ``reference``, ``residues``, ``online_filter``) stays the
reference implementation and runs the batched closed loop; these are its equations, held to its
residues by ``tests/test_numeric_filter.py``."""
