"""The air-traffic baseline, an IMM of constant-velocity and coordinated-turn models
(``reference``; its compiled loop is in filters.tracker.kernel, beside the Kalman tracker's)."""

from filters.turn.reference import *  # noqa: F401,F403  the public names
