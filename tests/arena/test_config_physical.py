"""The lab check refuses physically absurd values itself, naming the lab file's key (issue 20):
marker ids the lab's ArUco dictionary lacks, robot heights the tracker refuses, lens heights
and nadirs no lab has, and a lens below the robots."""

from __future__ import annotations

import pytest

from arena.config import ConfigError, parse_lab_config


def lab(**tables):
    return parse_lab_config(tables, "lab.toml")


@pytest.mark.parametrize("tables,expected", [
    ({"robots": [{"name": "zumo7", "marker_id": 60}]},
     r"robots\[0\]\.marker_id: expected an integer in \[0, 49\].*DICT_4X4_50.*'zumo7', got 60"),
    ({"robots": [{"name": "zumo7", "marker_id": 50}]}, r"robots\[0\]\.marker_id: .*\[0, 49\].*got 50"),
    ({"robots": [{"name": "zumo7", "marker_id": True}]}, r"robots\[0\]\.marker_id: .*got True"),
    ({"robots": [{"name": "z", "robot_height_cm": 100}]}, r"robots\[0\]\.robot_height_cm: expected .*\[0, 100\).*got 100"),
    ({"robots": [{"name": "z", "robot_height_cm": float("nan")}]}, r"robots\[0\]\.robot_height_cm: .*got nan"),
    ({"cameras": [{"name": "c", "camera_height_m": 250}]}, r"cameras\[0\]\.camera_height_m: .*\[0\.3, 20\] m, got 250"),
    ({"cameras": [{"name": "c", "camera_height_m": 0.1}]}, r"cameras\[0\]\.camera_height_m: .*got 0\.1"),
    ({"cameras": [{"name": "c", "camera_height_m": "2.5"}]}, r"cameras\[0\]\.camera_height_m: .*got '2\.5'"),
    ({"cameras": [{"name": "c", "nadir_m": [9.0, 0.5]}]}, r"cameras\[0\]\.nadir_m: .*within 2 arena sides.*got \[9\.0, 0\.5\]"),
    ({"arena": {"size_m": [1.0, 1.0]}, "cameras": [{"name": "c", "nadir_m": [-2.5, 0.5]}]}, r"cameras\[0\]\.nadir_m"),
    ({"cameras": [{"name": "c", "camera_height_m": 0.5}], "robots": [{"name": "z", "robot_height_cm": 60}]},
     r"cameras\[0\]\.camera_height_m: expected a lens height above the robots \(robots\[0\]\.robot_height_cm = 60 cm\)"),
    ({"cameras": [{"name": "c", "camera_height_m": 0.5}], "services": {"tracker": {"robot_height_cm": 55}}},
     r"cameras\[0\]\.camera_height_m: .*services\.tracker\.robot_height_cm = 55 cm"),
    ({"services": {"tracker": {"robot_height_cm": 100}}}, r"services\.tracker\.robot_height_cm: .*\[0, 100\), got 100"),
    ({"services": {"tracker": {"camera_height_m": 0.1}}}, r"services\.tracker\.camera_height_m: .*\[0\.3, 20\], got 0\.1"),
])
def test_absurd_geometry_is_refused_naming_the_key(tables, expected):
    with pytest.raises(ConfigError, match=expected):
        lab(**tables)


def test_the_edges_of_the_physical_ranges_are_accepted():
    cfg = lab(arena={"size_m": [2.0, 1.0]},
              cameras=[{"name": "lo", "camera_height_m": 0.3, "nadir_m": [-4.0, 0.5]},
                       {"name": "hi", "camera_height_m": 20, "nadir_m": [1.0, 4.9]}],
              robots=[{"name": "a", "marker_id": 0, "robot_height_cm": 0}, {"name": "b", "marker_id": 49,
                                                                            "robot_height_cm": 29.9}],
              services={"tracker": {"robot_height_cm": 3.2, "camera_height_m": 2.5}})
    assert [c.camera_height_m for c in cfg.cameras] == [0.3, 20.0]
    assert [c.nadir_m for c in cfg.cameras] == [(-4.0, 0.5), (1.0, 4.9)]
    assert [r.marker_id for r in cfg.robots] == [0, 49]
    assert cfg.robot_height_cm() == pytest.approx(14.95)
