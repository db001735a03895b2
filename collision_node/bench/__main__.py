"""Run ``python -m collision_node.bench SUBCOMMAND [options]``."""

import sys

from . import main

sys.exit(main())
