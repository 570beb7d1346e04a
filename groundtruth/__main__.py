"""``python -m groundtruth ...`` is ``arena groundtruth ...``."""

import sys

from arena.cli import main

sys.exit(main(["groundtruth", *sys.argv[1:]]))
