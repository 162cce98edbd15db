"""``python -m pipeline.recompute``: kept as a command and an import path; the code is in
``pipeline.results.recompute``."""

import sys

from pipeline.results.recompute import *  # noqa: F401,F403
from pipeline.results.recompute import main

if __name__ == "__main__":
    sys.exit(main())
