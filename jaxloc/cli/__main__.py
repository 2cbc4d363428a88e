"""``python -m jaxloc.cli``."""

import sys

from jaxloc.cli import main

sys.exit(main())
