"""Study 000's maneuvering-input estimators (MIE A, B, C): ``reference`` numpy, ``kernel``
the compiled scans checked against it."""

from filters.input_estimation.reference import *  # noqa: F401,F403  the public names
