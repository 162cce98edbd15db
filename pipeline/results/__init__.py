"""Reading stored runs: SQL over every table, reproduction reports, sweeps at a glance,
recomputing a stored run's metrics."""
