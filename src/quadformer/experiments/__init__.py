"""Experiments on top of the library: the paper's configuration grid and profiles, the
dataset and tuned-model caches, the detection benchmark and the resilience benchmark."""
