"""`arena sim` shells: plain (no ArUco marker) unless ``--markers``; the webcam shows what the
specs say (no marker to decode on a plain shell, each marker's id on a marked one)."""

from __future__ import annotations

import argparse

import numpy as np

from groundtruth.homography import homography_from_calibration
from groundtruth.rgb import MarkerDetector
from simulator.cli import _robots_from_args, add_arguments
from simulator.webcam import WebcamModel
from simulator.world import World


def _specs(*argv: str):
    p = argparse.ArgumentParser()
    add_arguments(p)
    return _robots_from_args(p.parse_args(list(argv)))[0]


def test_sim_robots_have_no_markers_unless_asked():
    plain = _specs("--robots", "3")
    assert [s.marker_id for s in plain] == [None, None, None]
    marked = _specs("--robots", "3", "--markers")
    assert [s.marker_id for s in marked] == [0, 1, 2]
    assert [s.name for s in plain] == [s.name for s in marked]


def test_sim_markers_fill_in_a_lab_config_without_marker_ids(tmp_path):
    lab = tmp_path / "lab.toml"
    lab.write_text('[[robots]]\nname = "zumo1"\ncolor = "red"\nmarker_id = 1\n\n'
                   '[[robots]]\nname = "zumo2"\ncolor = "blue"\n')
    assert [s.marker_id for s in _specs("--lab", str(lab))] == [1, None]       # the lab's ids kept
    assert [s.marker_id for s in _specs("--lab", str(lab), "--markers")] == [1, 0]


def test_the_webcam_shows_markers_only_on_marked_shells():
    for argv, ids in ((("--robots", "2"), set()), (("--robots", "2", "--markers"), {0, 1})):
        w = World(_specs(*argv))
        model = WebcamModel(w, noise=False)
        frame = model.render()
        det = MarkerDetector(None, homography_from_calibration(model.calibration))
        assert {i for i, _ in det.corners_px(frame)} == ids, argv
        # a plain shell shows its colour on top, with a dark strip across its front
        if not ids:
            spec, (x, y, yaw) = w.robots[1], w.pose(1)
            top = model.project(np.array([[x, y, model.shell_height_m]]))[0]
            front = model.project(np.array([[x + 0.031 * np.cos(yaw), y + 0.031 * np.sin(yaw),
                                             model.shell_height_m]]))[0]
            c = frame[int(round(top[1])), int(round(top[0]))].astype(int)[::-1]
            f = frame[int(round(front[1])), int(round(front[0]))].astype(int)
            assert np.abs(c - np.array(spec.color_rgb)).max() < 40, (c, spec.color_rgb)
            assert f.max() < 60, f
