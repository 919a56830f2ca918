"""The command line: ``jaxreg demo | pose | basin``, its reports, pictures and 3D view. May
import every other package.
"""

from jaxreg.cli.commands import main as main
from jaxreg.core._lazy import exports

# jaxreg.cli.<module> without importing it first; dir() lists the public names
__getattr__, __dir__ = exports(__name__, {})
