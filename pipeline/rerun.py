"""``python -m pipeline.rerun <run> [key=value ...]``: a stored run re-run with its own config into the
artifacts tree; the code is in ``pipeline.results.rerun``."""

import sys

from pipeline.results.rerun import *  # noqa: F401,F403
from pipeline.results.rerun import main

if __name__ == "__main__":
    sys.exit(main())
