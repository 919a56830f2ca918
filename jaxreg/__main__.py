"""``python -m jaxreg``: the command line (see :mod:`jaxreg.cli.commands`)."""

import sys

from jaxreg.cli.commands import main

sys.exit(main())
