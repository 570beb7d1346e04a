"""Arena: the contract every service shares (keys, messages, config, Zenoh session, CLI)."""

import os as _os

__version__ = "0.1.0"


def _numba_cache_fallback() -> None:
    """Give numba a cache directory it can write when it has none.

    The kernels are compiled with ``cache=True``, and numba raises at import ("cannot cache
    function ...: no locator available") when it can write neither beside the installed sources
    nor in ``~/.cache/numba``: a root-owned install run by another user with a read-only home,
    as under the systemd units' ``ProtectSystem=strict``. Then the cache goes to the temp
    directory (set ``NUMBA_CACHE_DIR``, e.g. the units' ``CacheDirectory``, to keep it).
    Runs before numba is imported (numba reads the variable once)."""
    if _os.environ.get("NUMBA_CACHE_DIR"):
        return
    here = _os.path.dirname(_os.path.abspath(__file__))
    pycache = _os.path.join(here, "__pycache__")
    if _os.access(pycache if _os.path.isdir(pycache) else here, _os.W_OK):
        return                                   # numba caches beside the sources
    import tempfile

    user = _os.path.join(_os.environ.get("XDG_CACHE_HOME") or _os.path.expanduser("~/.cache"), "numba")
    try:
        _os.makedirs(user, exist_ok=True)
        tempfile.TemporaryFile(dir=user).close()
        return                                   # numba's user-wide cache works
    except OSError:
        pass
    _os.environ["NUMBA_CACHE_DIR"] = _os.path.join(tempfile.gettempdir(), f"arena-numba-{_os.getuid()}")


_numba_cache_fallback()
