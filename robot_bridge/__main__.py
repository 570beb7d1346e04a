"""``python -m robot_bridge ...`` = ``arena bridge ...``."""

import sys

from robot_bridge.cli import main

sys.exit(main())
