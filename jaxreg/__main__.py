"""``python -m jaxreg``: the command line (see :mod:`jaxreg.cli`)."""

import sys

from jaxreg.cli import main

sys.exit(main())
