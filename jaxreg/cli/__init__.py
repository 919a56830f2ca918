"""The command line: ``jaxreg demo | pose | basin``, its reports, pictures and 3D view. May
import every other package.
"""

from jaxreg.cli.commands import main as main
from jaxreg.core._lazy import submodule as _submodule


def __getattr__(name: str):  # jaxreg.cli.<module> without importing it first
    return _submodule(__name__, name)
