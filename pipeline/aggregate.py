"""``python -m pipeline.aggregate``: kept as a command and an import path; the code is in
``pipeline.launch.aggregate``."""

import sys

from pipeline.launch.aggregate import *  # noqa: F401,F403
from pipeline.launch.aggregate import main

if __name__ == "__main__":
    sys.exit(main())
