"""Hydra launcher ``hydra/launcher=isolated``: every sweep job in its own fresh process, at most
``n_jobs`` at a time, so a job whose process is killed (the out-of-memory killer's SIGKILL, a crash in
native code) fails that job only. joblib's pooled workers cannot: one dead worker raises
TerminatedWorkerError out of the whole Parallel call and the sweep stops (issue 16, item 8)."""
