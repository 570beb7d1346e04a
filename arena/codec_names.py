"""Names of the event-window codecs (see :mod:`arena.codec`), importable without numba: command
lines list them as choices, and every service's start-up would otherwise pay for numba's import."""

DEFAULT_CODEC = "planes-zstd/1"
LOSSY_CODEC = "planes-zstd-ms/1"
RAW_CODEC = "raw/1"
CODECS = (DEFAULT_CODEC, LOSSY_CODEC, RAW_CODEC)

#: Most events one event window may decode to: the one limit of :func:`arena.codec.decode` and of
#: :class:`arena.messages.DecodeLimits` (13 B each decoded: 130 MB). A 10 ms window of a camera at
#: its 1 Gev/s peak.
MAX_WINDOW_EVENTS = 10_000_000
#: Most events per byte of a compressed window: every pixel of a 2047 x 2047 sensor firing in
#: the same µs codes at 757 events per byte (a 1280 x 720 flash: 627), while zstd frames of
#: repeated bytes reach 16 000: a 1 KB window can claim at most 2 M events (27 MB), not 10 M.
MAX_EVENTS_PER_BYTE = 2048
