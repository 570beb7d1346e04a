"""Cost of one viewer frame (the event image sent with an SSE snapshot) at lab event rates.

Ours (:class:`viewer.state.ViewerState`): each window is decoded once (to flat pixel and colour
indices) and kept for the accumulation period; a frame is one 1-byte-per-pixel index image written
as a palette PNG (:mod:`viewer.png`, zlib level 1), base64 for the data URL. Baseline: the straightforward version: decode every
window of the period again for each frame, draw ON and OFF with two masks into an RGB image, RGB
PNG by OpenCV at its default level (3). The images differ only where ON and OFF hit the same pixel within a slice (the baseline draws
every OFF after every ON; ours keeps the latest event). The viewer sends 10 frames/s per page.

Examples::

    python bench/bench_viewer.py
    python bench/bench_viewer.py --rate-mev 2 --width 1280 --height 720 --frames 30
"""

from __future__ import annotations

import argparse
import base64
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from arena import codec  # noqa: E402
from arena.events import make_events  # noqa: E402
from arena.messages import EventWindow  # noqa: E402
from viewer.png import encode_indexed_png  # noqa: E402
from viewer.state import OFF_RGB, ON_RGB, PALETTE, ViewerState  # noqa: E402


def make_windows(n: int, per_window: int, w: int, h: int, slice_us: int, seed: int = 0) -> list[EventWindow]:
    """``n`` windows of ``per_window`` events: 4 moving blobs (robots) plus 10 % uniform noise."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        blobs = per_window * 9 // 10
        cx = (np.arange(4) * w / 4 + w / 8 + k * 0.5) % w
        cy = np.full(4, h / 2) + np.arange(4) * 10
        i = rng.integers(0, 4, blobs)
        x = np.r_[cx[i] + rng.normal(0, 8, blobs), rng.uniform(0, w - 1, per_window - blobs)]
        y = np.r_[cy[i] + rng.normal(0, 8, blobs), rng.uniform(0, h - 1, per_window - blobs)]
        t = np.sort(rng.integers(k * slice_us, (k + 1) * slice_us, per_window))
        ev = make_events(np.clip(x, 0, w - 1).astype(int), np.clip(y, 0, h - 1).astype(int),
                         rng.integers(0, 2, per_window), t)
        out.append(EventWindow(camera="cam0", seq=k, t_start_us=k * slice_us, t_end_us=(k + 1) * slice_us,
                               width=w, height=h, count=ev.size, codec=codec.DEFAULT_CODEC, data=codec.encode(ev)))
    return out


def baseline_frame(windows: list[EventWindow], w: int, h: int) -> tuple[np.ndarray, str]:
    img = np.full((h, w, 3), 255, np.uint8)
    for win in windows:
        ev = codec.decode(win.codec, win.data, win.count)
        on = ev["p"] == 1
        img[ev["y"][on], ev["x"][on]] = ON_RGB
        img[ev["y"][~on], ev["x"][~on]] = OFF_RGB
    ok, buf = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    return img, "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rate-mev", type=float, default=1.0, help="event rate, million events/s (default 1)")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--slice-ms", type=float, default=10.0, help="edge slice length (default 10 ms)")
    ap.add_argument("--accumulate-ms", type=float, default=100.0)
    ap.add_argument("--frames", type=int, default=20, help="frames timed (one new slice per frame)")
    a = ap.parse_args()
    slice_us = int(a.slice_ms * 1000)
    per_window = int(a.rate_mev * 1e6 * a.slice_ms / 1000)
    k = int(a.accumulate_ms / a.slice_ms)
    wins = make_windows(k + a.frames, per_window, a.width, a.height, slice_us)
    codec.decode(wins[0].codec, wins[0].data, wins[0].count)  # compile/load numba before timing

    st = ViewerState(accumulate_us=int(a.accumulate_ms * 1000))
    for win in wins[:k]:
        st.on_window(win)
    st.render_frame()
    t_ours, t_base, size_ours, size_base = [], [], [], []
    for f in range(a.frames):
        new = wins[k + f]
        t0 = time.perf_counter()
        st.on_window(new)
        url = "data:image/png;base64," + base64.b64encode(encode_indexed_png(st.render_index(), PALETTE)).decode()
        t_ours.append(time.perf_counter() - t0)
        size_ours.append(len(url))
        t0 = time.perf_counter()
        _, url_b = baseline_frame(wins[f + 1:k + f + 1], a.width, a.height)
        t_base.append(time.perf_counter() - t0)
        size_base.append(len(url_b))
    ours, base = np.median(t_ours) * 1e3, np.median(t_base) * 1e3
    print(f"viewer frame: {a.width}x{a.height} px, {a.rate_mev:g} Mev/s, last {a.accumulate_ms:g} ms "
          f"({k} slices, {k * per_window} events), {a.frames} frames, median")
    print(f"{'':<28}{'ours':>10}{'baseline':>12}{'ratio':>9}")
    print(f"{'time per frame (ms)':<28}{ours:>10.1f}{base:>12.1f}{base / ours:>8.1f}x")
    print(f"{'frame size (kB, base64)':<28}{np.median(size_ours) / 1e3:>10.1f}{np.median(size_base) / 1e3:>12.1f}"
          f"{np.median(size_base) / np.median(size_ours):>8.2f}x")
    print(f"{'CPU at 10 frames/s (%)':<28}{ours:>10.1f}{base:>12.1f}")


if __name__ == "__main__":
    main()
