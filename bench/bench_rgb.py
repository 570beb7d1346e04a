"""RGB ground truth: accuracy and speed of our detectors vs the paper's plain HSV centroid.

Scene: the simulator's webcam (640x480, 24 fps, JPEG q90 like the MJPEG stream) over 4 and 8
robots driving circles at 100 % and 50 % power; errors against the simulator's exact poses.

* baseline  — the paper's method: HSV threshold, findContours, largest blob, centroid by
  moments, mapped with the homography of the four mat corners clicked on the floor; heading
  from the frame-to-frame motion.
* ours hsv  — groundtruth.rgb.HsvDetector (morphology, area/shape checks, hull centroid,
  shell-top homography, front mark / motion heading).
* ours aruco — groundtruth.rgb.MarkerDetector (ArUco 4x4 ids, sub-pixel corners).

Also prints the detectors under dimmed and dark light and the webcam model's render cost (ms/frame) for 1, 4, 8 and 16 robots.

Usage: python bench/bench_rgb.py [--seconds 10]
"""

from __future__ import annotations

import argparse
import math
import time

import cv2
import numpy as np

from groundtruth.homography import homography_from_calibration
from groundtruth.rgb import HsvDetector, MarkerDetector, sample_hsv_range
from simulator.webcam import WebcamModel
from simulator.world import RobotSpec, World

COLOURS = [(220, 40, 40), (40, 180, 60), (40, 80, 220), (230, 200, 30),
           (200, 60, 200), (240, 130, 30), (40, 200, 200), (120, 40, 220)]


def scene(n: int, markers: bool, seed: int = 0) -> World:
    cols = 2 if n <= 4 else 4
    cw, ch = 1.83 / cols, 1.83 / 2
    robots = [RobotSpec(f"r{i}", COLOURS[i % 8], marker_id=i if markers else None,
                        start=((i % cols + 0.5) * cw, (i // cols % 2 + 0.5) * ch - 0.12, 0.0))
              for i in range(n)]
    w = World(robots, seed=seed)
    for i in range(n):
        w.set_power(i, *((400, 160) if i % 2 == 0 else (200, 80)))
    return w


class PaperBaseline:
    """HSV + findContours + centroid by moments, floor homography, heading from motion."""

    name = "baseline"

    def __init__(self, ranges, homography):
        self.ranges, self.h = ranges, homography
        self.prev: dict[str, tuple[float, float]] = {}

    def detect(self, frame, t_us):
        hsv = cv2.cvtColor(frame, cv2.COLOR_BGR2HSV)
        out = []
        for name, rng in self.ranges.items():
            cs, _ = cv2.findContours(rng.mask(hsv), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            if not cs:
                continue
            c = max(cs, key=cv2.contourArea)
            m = cv2.moments(c)
            if m["m00"] <= 0:
                continue
            x, y = self.h.to_arena(np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]]))
            px, py = self.prev.get(name, (x, y))
            yaw = math.atan2(y - py, x - px) if math.hypot(x - px, y - py) > 1e-3 else float("nan")
            self.prev[name] = (x, y)
            out.append(type("D", (), {"robot": name, "x_m": x, "y_m": y, "yaw_rad": yaw}))
        return out


def evaluate(n: int, kind: str, seconds: float, lighting: str = "full") -> dict:
    """Run one detector; colour ranges are sampled in full light (at set-up), then the
    light is set to ``lighting``."""
    w = scene(n, markers=(kind == "aruco"))
    m = WebcamModel(w)
    top = homography_from_calibration(m.calibration)
    if kind == "aruco":
        det = MarkerDetector({i: f"r{i}" for i in range(n)}, top)
    else:
        frame = m.render()
        ranges = {}
        for i, spec in enumerate(w.robots):
            x, y, _ = w.pose(i)
            ranges[spec.name] = sample_hsv_range(frame, m.project([[x, y, m.shell_height_m]])[0])
        if kind == "hsv":
            det = HsvDetector(ranges, top)
        else:
            det = PaperBaseline(ranges, homography_from_calibration(m.calibration, "floor_points"))
    w.lighting = lighting
    pos, yaw, found, t_det = [], [], 0, 0.0
    frames = int(seconds * 24)
    for _ in range(frames):
        w.step(1 / 24)
        ok, buf = cv2.imencode(".jpg", m.render(), [cv2.IMWRITE_JPEG_QUALITY, 90])
        frame = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        t0 = time.perf_counter()
        dets = {d.robot: d for d in det.detect(frame, int(w.t * 1e6))}
        t_det += time.perf_counter() - t0
        truth = w.poses()
        for i, spec in enumerate(w.robots):
            d = dets.get(spec.name)
            if d is None:
                continue
            found += 1
            pos.append(100 * math.hypot(d.x_m - truth[i, 0], d.y_m - truth[i, 1]))
            if not math.isnan(d.yaw_rad):
                yaw.append(math.degrees(abs((d.yaw_rad - truth[i, 2] + math.pi) % (2 * math.pi) - math.pi)))
    def stat(a, q):
        return float(np.percentile(a, q)) if len(a) else float("nan")

    return {"pos_med": stat(pos, 50), "pos_p95": stat(pos, 95), "yaw_med": stat(yaw, 50),
            "yaw_p95": stat(yaw, 95), "recall": found / (frames * n), "fps": frames / t_det}


def render_cost(n: int, frames: int = 48) -> float:
    robots = [RobotSpec(f"r{i}", COLOURS[i % 8], marker_id=i if i % 2 else None,
                        start=(0.2 + 0.45 * (i % 4), 0.2 + 0.45 * (i // 4), 0.4 * i)) for i in range(n)]
    w = World(robots)
    for i in range(n):
        w.set_power(i, 400, 300)
    m = WebcamModel(w)
    m.render()
    t = 0.0
    for _ in range(frames):
        w.step(1 / 24)
        t0 = time.perf_counter()
        m.render()
        t += time.perf_counter() - t0
    return t / frames * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=10.0, help="simulated seconds per run (default 10)")
    args = ap.parse_args()
    print(f"RGB ground truth, 640x480 @ 24 fps, JPEG q90, {args.seconds:g} s per run; errors vs exact truth\n")
    hdr = f"{'n':>2} {'detector':<9} {'pos med cm':>10} {'pos p95':>8} {'yaw med °':>9} {'yaw p95':>8} {'recall':>7} {'det fps':>8}"
    for n in (4, 8):
        print(hdr)
        res = {k: evaluate(n, k, args.seconds) for k in ("baseline", "hsv", "aruco")}
        for k, r in res.items():
            print(f"{n:>2} {k:<9} {r['pos_med']:>10.3f} {r['pos_p95']:>8.3f} {r['yaw_med']:>9.2f} "
                  f"{r['yaw_p95']:>8.2f} {r['recall']:>7.3f} {r['fps']:>8.0f}")
        b = res["baseline"]
        for k in ("hsv", "aruco"):
            r = res[k]
            print(f"   {k} vs baseline: position error x{b['pos_med'] / r['pos_med']:.1f} smaller, "
                  f"heading error x{b['yaw_med'] / r['yaw_med']:.1f} smaller, speed x{r['fps'] / b['fps']:.2f}")
        print()
    print("lighting (4 robots; colour ranges sampled in full light):")
    print(f"{'light':<7} {'detector':<9} {'pos med cm':>10} {'yaw med °':>9} {'recall':>7}")
    for light in ("dimmed", "dark"):
        for k in ("baseline", "hsv", "aruco"):
            r = evaluate(4, k, min(args.seconds, 5.0), light)
            print(f"{light:<7} {k:<9} {r['pos_med']:>10.3f} {r['yaw_med']:>9.2f} {r['recall']:>7.3f}")
    print()
    print("webcam model render cost (ms/frame; 24 fps real time needs < 41.7):")
    for n in (1, 4, 8, 16):
        print(f"  {n:>2} robots: {render_cost(n):6.2f} ms")


if __name__ == "__main__":
    main()
