"""A job: its config read once and checked, the declared stages run in order through the cache,
its status, memory estimate, progress and environment."""
