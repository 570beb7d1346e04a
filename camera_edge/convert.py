"""``arena convert IN OUT``: convert event recordings between formats, streaming chunk by chunk.

Formats are chosen by extension (see :mod:`arena.formats`); sensor size and the sensor's
absolute timestamps are kept. Events outside the sensor (corrupt input) are counted and skipped.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from arena.formats import FormatError, iter_events, open_writer


def convert(src: str | Path, dst: str | Path, evt: int = 3, compression: str = "lz4",
            width: int | None = None, height: int | None = None, progress: bool = False) -> dict:
    """Convert ``src`` to ``dst``; returns counts ``{"events", "invalid", "width", "height"}``.

    ``evt`` (3 or 2) applies when ``dst`` is ``.raw``; ``compression`` when it is ``.aedat4``;
    ``width``/``height`` override the sensor size (needed for CSV/npy without it).
    Raises :class:`FormatError` for unknown formats and corrupt input.
    """
    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve():
        raise FormatError("input and output are the same file")
    opts = {}
    if src.suffix.lower() in (".csv", ".npy", ".npz") and (width or height):
        opts = {"width": width, "height": height}
    wopts: dict = {}
    if dst.suffix.lower() == ".raw":
        wopts["evt"] = evt
    elif dst.suffix.lower() == ".aedat4":
        wopts["compression"] = compression
    n = 0
    with iter_events(src, **opts) as reader:
        w, h = width or reader.width, height or reader.height
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=os.path.getsize(src), unit="B", unit_scale=True, desc=src.name, file=sys.stderr)
        try:
            with open_writer(dst, w, h, **wopts) as writer:
                for chunk in reader:
                    writer.write(chunk)
                    n += chunk.size
                    if bar is not None:
                        f = getattr(reader, "_f", None)
                        bar.n = f.tell() if f is not None and not f.closed else bar.total
                        bar.refresh()
        except BaseException:
            dst.unlink(missing_ok=True)  # never leave a half-written file behind
            raise
        finally:
            if bar is not None:
                bar.close()
        return {"events": n, "invalid": reader.invalid, "width": w, "height": h}
