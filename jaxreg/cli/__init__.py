"""The command line: ``jaxreg demo | pose | basin``, its reports, pictures and 3D view. May
import every other package.
"""

from jaxreg.cli.commands import main as main
