"""Stage functions: pure functions of in-memory arrays; the runner does the I/O and caching."""
