"""`python -m simulator`: the same as `arena sim`."""

import sys

from simulator.cli import main

sys.exit(main())
