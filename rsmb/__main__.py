"""``python -m rsmb``: the command line."""

import sys

from rsmb.pipeline.cli import main

sys.exit(main())
