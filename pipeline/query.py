"""``python -m pipeline.query``: kept as a command and an import path; the code is in
``pipeline.results.query``."""

import sys

from pipeline.results.query import *  # noqa: F401,F403
from pipeline.results.cli import main    # the query and tracking commands, as mtt-query

if __name__ == "__main__":
    sys.exit(main())
