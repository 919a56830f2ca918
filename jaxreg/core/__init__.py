"""Building blocks every other package uses: the result base class and its status selection,
scalar leaves for configuration Modules, padded sizes, the host thread pool, exact
brute-force nearest neighbours (geometry's ADD-S and search's queries share them), the on-disk
store of compiled programs, and the opt-in switch (``enable_compilation_cache``) that keeps
compiled programs between processes.

Imports nothing from the rest of jaxreg.
"""

from jaxreg.core._lazy import exports

# The public names, each module imported on first use; jaxreg.core.<module> resolves too.
__getattr__, __dir__ = exports(
    __name__, {"jaxreg.core.compilation": ("default_cache_folder", "enable_compilation_cache")}
)
