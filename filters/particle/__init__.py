"""Study 004's multiple-model particle filters (AMMPF, SIR-MM): ``reference`` is the numpy scan,
``kernel`` the compiled one (the same random numbers, checked against it)."""

from filters.particle.reference import *  # noqa: F401,F403  the public names
