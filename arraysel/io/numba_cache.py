"""Where numba keeps the compiled code of arraysel's kernels (``cache=True``).

numba writes it next to the source (``__pycache__``) or in the user's cache folder
(``~/.cache/numba``), and a kernel module whose neither place can be written fails to import
("cannot cache function ...: no locator available"): an installation owned by another user run
by someone whose home cannot be written. :func:`ensure_cache_dir`, called by each kernel module
before its kernels are compiled, points numba at a folder of this user's own under the temporary
folder then (``NUMBA_CACHE_DIR``, when it is set, is left as it is).
"""
from __future__ import annotations

import os
import stat
import tempfile

__all__ = ["ensure_cache_dir", "fallback_dir"]


def fallback_dir() -> str:
    """``<temporary folder>/arraysel-numba-<uid>``: made, owned by this user and private (0700)."""
    uid = os.getuid() if hasattr(os, "getuid") else 0
    path = os.path.join(tempfile.gettempdir(), f"arraysel-numba-{uid}")
    os.makedirs(path, mode=0o700, exist_ok=True)
    st = os.lstat(path)
    if not stat.S_ISDIR(st.st_mode) or (hasattr(os, "getuid") and st.st_uid != uid):
        raise OSError(f"{path} is not a folder of this user")
    return path


def ensure_cache_dir(source_file: str) -> str | None:
    """Make sure numba can cache the kernels of ``source_file`` (a module's ``__file__``): where
    numba itself finds no writable place, set its cache folder to :func:`fallback_dir`. Returns
    the folder set (None when nothing had to change or nothing could be done: numba then says
    why when the kernels are compiled)."""
    try:
        import numba
        from numba.core import caching
    except ImportError:  # pragma: no cover - numba is a dependency
        return None
    if numba.config.CACHE_DIR:
        return None

    def probe():  # a function of this file, for numba's locators
        return None

    for cls in (caching.InTreeCacheLocator, caching.UserWideCacheLocator):
        try:
            if cls.from_function(probe, source_file) is not None:
                return None
        except Exception:  # noqa: BLE001 - a locator that fails is no place to cache in
            continue
    try:
        folder = fallback_dir()
    except OSError:
        return None
    numba.config.CACHE_DIR = folder
    return folder
