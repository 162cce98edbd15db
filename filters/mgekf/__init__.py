"""Study 003's sonar trackers (MGEKF, KF+MGEKF): ``reference`` numpy, ``kernel`` the compiled
scans checked against it."""

from filters.mgekf.reference import *  # noqa: F401,F403  the public names
