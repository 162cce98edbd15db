"""Study 002's bias registration (local tracks, the proposed pseudo-measurement filter, EX-X):
``reference`` numpy, ``kernel`` the compiled local-track step checked against it."""

from filters.bias.reference import *  # noqa: F401,F403  the public names
