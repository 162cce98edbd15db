"""``python -m pipeline.sweep``: kept as a command and an import path; the code is in
``pipeline.results.sweep``."""

import sys

from pipeline.results.sweep import *  # noqa: F401,F403
from pipeline.results.sweep import main

if __name__ == "__main__":
    sys.exit(main())
