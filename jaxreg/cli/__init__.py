"""The command line: ``jaxreg demo | pose | basin``, its reports, pictures and 3D view. May
import every other package.
"""

from jaxreg.cli.commands import main as main
from jaxreg.core._lazy import submodules

__getattr__ = submodules(__name__)  # jaxreg.cli.<module> without importing it first
