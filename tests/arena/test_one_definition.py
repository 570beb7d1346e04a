"""Contracts defined in one place: one homography fitter and one CalibrationError
(arena.homography), one Zenoh settings model and one list of modes (arena.config), one set of
track-state names (arena.messages)."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("arena", "camera_edge", "tracker", "robot_bridge", "groundtruth", "simulator", "viewer", "recorder",
            "demo", "ros2", "bench")
#: the simulator builds its true camera from four exact corners: the world it stands in for, not a
#: calibration (and it stays independent of the code it tests)
SIMULATOR_GEOMETRY = {"simulator/camera.py", "simulator/webcam.py"}


def _modules():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            yield rel, ast.parse(path.read_text(encoding="utf-8"), rel)


def _calls(tree: ast.AST, name: str) -> bool:
    return any(isinstance(n, ast.Attribute) and n.attr == name for n in ast.walk(tree))


def _classes(tree: ast.AST) -> set[str]:
    return {n.name for n in ast.walk(tree) if isinstance(n, ast.ClassDef)}


def test_one_homography_fitter_and_one_calibration_error():
    fitters, perspective, errors = [], [], []
    for rel, tree in _modules():
        if _calls(tree, "findHomography"):
            fitters.append(rel)
        if _calls(tree, "getPerspectiveTransform") and rel not in SIMULATOR_GEOMETRY:
            perspective.append(rel)
        if "CalibrationError" in _classes(tree):
            errors.append(rel)
    assert fitters == ["arena/homography.py"], "fit homographies with arena.homography.fit_homography"
    assert perspective == [], "fit homographies with arena.homography.fit_homography"
    assert errors == ["arena/homography.py"], "raise arena.homography.CalibrationError"


def test_the_services_calibration_errors_are_the_one_class():
    from arena.homography import CalibrationError
    from groundtruth.homography import CalibrationError as gt_error
    from tracker.calibration import CalibrationError as tracker_error

    assert gt_error is CalibrationError and tracker_error is CalibrationError


def test_one_zenoh_settings_model():
    from arena import config, session

    zenoh_classes = [(rel, c) for rel, tree in _modules() for c in _classes(tree) if c.startswith("Zenoh")]
    assert zenoh_classes == [("arena/config.py", "ZenohSettings")]
    assert session.ZenohSettings is config.ZenohSettings and session.MODES is config.MODES
    assert isinstance(config.LabConfig().zenoh, config.ZenohSettings)
    fields = {f.name for f in dataclasses.fields(config.ZenohSettings)}
    assert fields == {"mode", "connect", "listen", "multicast_scouting", "lease_ms", "config_file", "tls", "user",
                      "password", "cfg"}


def test_the_lab_zenoh_table_resolves_as_before(tmp_path):
    """The lab's [zenoh] table is a ZenohSettings: without connect a client still goes to the
    default router and a router connects to nothing; resolving does not change the lab's copy."""
    from arena.config import DEFAULT_ROUTER, parse_lab_config
    from arena.session import resolve_settings, to_zenoh_config

    lab = parse_lab_config({"zenoh": {"mode": "peer", "listen": ["tcp/0.0.0.0:7448"], "lease_ms": 500}})
    s = resolve_settings(None, lab)
    assert (s.mode, s.connect, s.listen, s.lease_ms) == ("peer", [DEFAULT_ROUTER], ["tcp/0.0.0.0:7448"], 500)
    s.listen.append("tcp/127.0.0.1:1")
    assert lab.zenoh.listen == ["tcp/0.0.0.0:7448"]
    assert resolve_settings(None, parse_lab_config({"zenoh": {"mode": "router"}})).connect == []
    assert resolve_settings(None, parse_lab_config({})).connect == [DEFAULT_ROUTER]
    conf = to_zenoh_config(s)
    assert conf.get_json("mode") == '"peer"' and s.to_zenoh_config().get_json("listen/endpoints") == \
        '["tcp/0.0.0.0:7448","tcp/127.0.0.1:1"]'


def test_one_set_of_track_states():
    from arena.messages import COASTING, CONFIRMED, TENTATIVE, TRACK_STATES, Track

    assert TRACK_STATES == (TENTATIVE, CONFIRMED, COASTING) == ("tentative", "confirmed", "coasting")
    assert Track.__dataclass_fields__["state"].metadata["choices"] is TRACK_STATES
