"""Colour ground truth of unmarked robots, as `arena demo` runs it by default: the simulator's
shells (no ArUco marker, a dark front window strip), ranges from the nominal shell colours (what
the demo passes as ``--robot NAME=#rrggbb``), frames through JPEG like the MJPEG stream.

The webcam model is used directly (no demo). Targets: position within 1 cm and heading within a
few degrees of the world's exact pose, in full and dimmed light, with the heading resolved by the
front mark; a near-white shell is refused with a message saying why.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from groundtruth.homography import homography_from_calibration
from groundtruth.rgb import HsvDetector, colour_detectable
from groundtruth.service import SetupError, build_detector, heading_counts, heading_note
from simulator.cli import layout_poses
from simulator.scenarios import Scenario
from simulator.webcam import WebcamModel
from simulator.world import World


def _world(lighting: str, n: int = 4) -> World:
    """The demo's first ``n`` robots (black, yellow, red, blue) without markers, at the demo's
    mixed layout, driving arcs (100 % power) and straight lines (75 %) alternately."""
    specs = Scenario(n_robots=n, markers=False).robot_specs()
    specs = [replace(s, start=p) for s, p in zip(specs, layout_poses("mixed", n, 1.83))]
    assert all(s.marker_id is None for s in specs)
    w = World(specs, lighting=lighting)
    for i in range(n):
        w.set_power(i, *((400, 160) if i % 2 == 0 else (300, 300)))
    return w


def _jpeg(frame: np.ndarray) -> np.ndarray:
    ok, buf = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, 90])
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)


def _errors(w: World, model: WebcamModel, det, frames: int):
    """Per robot name: position errors (cm), heading errors (deg), misses."""
    out = {s.name: ([], [], 0) for s in w.robots}
    for _ in range(frames):
        w.step(1 / 24)
        dets = {d.robot: d for d in det.detect(_jpeg(model.render()), int(w.t * 1e6))}
        truth = w.poses()
        for i, s in enumerate(w.robots):
            pos, yaw, miss = out[s.name]
            d = dets.get(s.name)
            if d is None:
                out[s.name] = (pos, yaw, miss + 1)
                continue
            pos.append(100 * math.hypot(d.x_m - truth[i, 0], d.y_m - truth[i, 1]))
            if not math.isnan(d.yaw_rad):
                yaw.append(math.degrees(abs((d.yaw_rad - truth[i, 2] + math.pi) % (2 * math.pi) - math.pi)))
    return out


def _demo_detector(w: World, model: WebcamModel):
    """The detector `arena groundtruth --detector hsv --robot NAME=#rrggbb ...` builds in the demo."""
    colours = {s.name: tuple(int(c) for c in s.color_rgb) for s in w.robots}
    return build_detector("hsv", homography_from_calibration(model.calibration), colours=colours)


@pytest.mark.parametrize("lighting", ["full", "dimmed"])
def test_unmarked_robots_by_colour_within_a_centimetre_and_a_few_degrees(lighting):
    w = _world(lighting)
    model = WebcamModel(w)
    det = _demo_detector(w, model)
    assert isinstance(det, HsvDetector)
    errs = _errors(w, model, det, 36)
    for name, (pos, yaw, miss) in errs.items():
        pos, yaw = np.array(pos), np.array(yaw)
        assert miss == 0, (lighting, name, miss)
        assert np.median(pos) <= 0.5 and np.percentile(pos, 95) <= 1.0, (lighting, name, np.median(pos), pos.max())
        assert len(yaw) == len(pos), (lighting, name)             # every heading resolved
        assert np.median(yaw) <= 2.0 and yaw.max() <= 5.0, (lighting, name, np.median(yaw), yaw.max())
    # the dark front window strip resolved the square shell's 90-degree ambiguity, not the motion
    n = sum(len(p) for p, _, _ in errs.values())
    assert det.heading_sources == {"front_mark": n, "motion": 0, "unknown": 0}, det.heading_sources
    assert heading_counts(det) == f"headings: {n} from the front mark, 0 from motion, 0 unknown"
    assert "front mark" in heading_note(det)
    if lighting == "dimmed":         # the V bounds followed the mats' brightness down
        assert 0.4 < det.v_scale < 0.6, det.v_scale


def test_without_front_mark_the_heading_comes_from_motion_and_says_so():
    w = _world("full", n=2)
    model = WebcamModel(w)
    colours = {s.name: tuple(int(c) for c in s.color_rgb) for s in w.robots}
    det = build_detector("hsv", homography_from_calibration(model.calibration), colours=colours, front_mark=False)
    errs = _errors(w, model, det, 24)
    src = det.heading_sources
    assert src["front_mark"] == 0 and src["motion"] >= 30 and src["unknown"] >= 2, src   # unknown until it moved
    yaw = np.concatenate([y for _, y, _ in errs.values()])
    assert np.median(yaw) <= 5.0
    assert heading_note(det).endswith("resolved by the direction of motion (no front mark)")


def test_near_white_shells_are_refused_with_the_reason():
    white = Scenario(n_robots=6, markers=False).robot_specs()[5]
    assert white.name == "white5"
    why = colour_detectable(white.color_rgb)
    assert why is not None and "too close to the white mats" in why
    for s in Scenario(n_robots=5, markers=False).robot_specs():   # black, yellow, red, blue, green
        assert colour_detectable(s.color_rgb) is None, s
    h = homography_from_calibration(WebcamModel(_world("full", n=1)).calibration)
    with pytest.raises(SetupError, match="white5: shell colour .* too close to the white mats"):
        build_detector("hsv", h, colours={"black0": (25, 25, 25), "white5": tuple(white.color_rgb)})
