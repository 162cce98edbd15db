"""Truth generators. Each is a config node with ``_target_`` and a ``generate(runs, seed)``."""
