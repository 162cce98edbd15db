"""The Kalman trackers on Cartesian and polar measurements (KalmanTracker: CV, CA, Singer):
``reference`` is the numpy filter the compiled ``kernel`` is checked against. The kernel also
holds the CV/CT IMM's loop (filters.turn): numba's cache checks only the file of the function it
compiles, so loops that share helpers share a file."""

from filters.tracker.reference import *  # noqa: F401,F403  the public names
