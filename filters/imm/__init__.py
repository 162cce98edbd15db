"""Study 001's IMMs (FSIMM, VSIMM, AO-VSIMM): ``reference`` is the numpy IMM cycle and the
model-set logic, ``kernel`` the compiled cycle it is checked against."""

from filters.imm.reference import *  # noqa: F401,F403  the public names
