"""Measurement synthesis. Each sensor is a config node with ``_target_`` and ``measure(truth, seed)``."""
