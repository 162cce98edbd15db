"""``python -m pipeline.report``: kept as a command and an import path; the code is in
``pipeline.results.report``."""

import sys

from pipeline.results.report import *  # noqa: F401,F403
from pipeline.results.report import main

if __name__ == "__main__":
    sys.exit(main())
