"""Opt-in caches of compiled programs, so that a fresh process does not compile again.

:func:`enable_compilation_cache` turns on, for the calling process, JAX's persistent
compilation cache (XLA's compile step is looked up instead of run) and, in its ``programs``
folder, jaxreg's store of whole executables (:mod:`jaxreg.core._program_cache`: a stored
program is loaded with no tracing or lowering either). Nothing calls it on import: it changes
JAX's configuration, which is the caller's to change. The command line calls it.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["default_cache_folder", "enable_compilation_cache"]


def default_cache_folder() -> str | None:
    """``$JAXREG_CACHE_DIR`` if set (``""``: None, caching off), else
    ``$XDG_CACHE_HOME/jaxreg/jax`` (``~/.cache/jaxreg/jax``)."""
    folder = os.environ.get("JAXREG_CACHE_DIR")
    if folder is None:
        base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
        folder = str(Path(base) / "jaxreg" / "jax")
    return folder or None


def enable_compilation_cache(path: str | os.PathLike | None = None) -> str | None:
    """Keeps this process's compiled programs on disk and reuses those of earlier processes.

    Sets JAX's ``jax_compilation_cache_dir`` to ``path`` (with no minimum compile time or
    entry size, so the many small programs of a first call are kept too) and jaxreg's program
    store to ``path/programs``. A later process that calls this with the same folder loads
    :func:`jaxreg.icp`'s and the pipeline's programs instead of tracing, lowering and
    compiling them (on one 2-core CPU: the first ICP of a fresh process in a fraction of a
    second instead of 2-3 s). The folder is trusted code: do not share it with users you do
    not trust. Deleting it is always safe.

    Call it before the first jaxreg call whose compile should be kept; programs compiled
    earlier in the process are not written back.

    Args:
        path: the folder (created if missing). ``None``: :func:`default_cache_folder`.

    Returns:
        The folder in use, or None when ``path`` is None and ``$JAXREG_CACHE_DIR`` is ``""``
        (both caches left off).
    """
    import jax

    from jaxreg.core import _program_cache

    folder = default_cache_folder() if path is None else os.fspath(path)
    if not folder:
        return None
    Path(folder).mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _program_cache.set_folder(Path(folder) / "programs")
    return folder
