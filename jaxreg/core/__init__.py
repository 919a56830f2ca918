"""Building blocks every other package uses: the result base class and its status selection,
scalar leaves for configuration Modules, and the on-disk store of compiled programs.

Imports nothing from the rest of jaxreg.
"""
