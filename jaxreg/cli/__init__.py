"""The command line: ``jaxreg demo | pose | basin``, its reports and pictures. May import every
other package.
"""

from jaxreg.cli.commands import main as main
