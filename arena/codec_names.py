"""Names of the event-window codecs (see :mod:`arena.codec`), importable without numba: command
lines list them as choices, and every service's start-up would otherwise pay for numba's import."""

DEFAULT_CODEC = "planes-zstd/1"
LOSSY_CODEC = "planes-zstd-ms/1"
RAW_CODEC = "raw/1"
CODECS = (DEFAULT_CODEC, LOSSY_CODEC, RAW_CODEC)
