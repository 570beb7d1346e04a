"""``python -m camera_edge ...`` = ``arena edge ...``."""

import sys

from arena.cli import main

if __name__ == "__main__":
    sys.exit(main(["edge", *sys.argv[1:]]))
