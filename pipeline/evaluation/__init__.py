"""From estimates to numbers: the metric registry, per-step metrics, the Monte Carlo
uncertainty of every summary value and paired comparison, bounds and numerical faults."""
