import arena  # noqa: F401 - first, so that numba has a writable cache directory (arena._numba_cache_fallback)
