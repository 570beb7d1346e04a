"""Arena: the contract every service shares (keys, messages, config, Zenoh session, CLI)."""

import os as _os

__version__ = "0.1.0"


def numba_writes_beside(pkg_dir: str) -> bool:
    """Whether numba can cache the kernels of the package in ``pkg_dir`` in its ``__pycache__``."""
    pycache = _os.path.join(pkg_dir, "__pycache__")
    return _os.access(pycache if _os.path.isdir(pycache) else pkg_dir, _os.W_OK)


def numba_user_cache() -> str:
    """numba's user-wide cache directory (``$XDG_CACHE_HOME/numba`` or ``~/.cache/numba``)."""
    return _os.path.join(_os.environ.get("XDG_CACHE_HOME") or _os.path.expanduser("~/.cache"), "numba")


def _numba_cache_fallback() -> None:
    """Give numba a cache directory it can write when it has none.

    The kernels are compiled with ``cache=True``, and numba raises at import ("cannot cache
    function ...: no locator available") when it can write neither beside the installed sources
    nor in ``~/.cache/numba``: a root-owned install run by another user with a read-only home,
    as under the systemd units' ``ProtectSystem=strict``. Then the cache goes to the temp
    directory (set ``NUMBA_CACHE_DIR``, e.g. the units' ``CacheDirectory``, to keep it).
    Runs before numba is imported (numba reads the variable once)."""
    if _os.environ.get("NUMBA_CACHE_DIR") or numba_writes_beside(_os.path.dirname(_os.path.abspath(__file__))):
        return
    import tempfile

    try:
        _os.makedirs(numba_user_cache(), exist_ok=True)
        tempfile.TemporaryFile(dir=numba_user_cache()).close()
        return                                   # numba's user-wide cache works
    except OSError:
        pass
    _os.environ["NUMBA_CACHE_DIR"] = _os.path.join(tempfile.gettempdir(), f"arena-numba-{_os.getuid()}")


_numba_cache_fallback()
