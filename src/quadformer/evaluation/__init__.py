"""Honest evaluation: detection metrics, the split / tuning protocol, resilience metrics."""
