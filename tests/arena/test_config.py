from pathlib import Path

import pytest

from arena.config import ConfigError, load_lab_config

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "deploy" / "lab.example.toml"


def test_example_config_matches_the_papers_lab():
    lab = load_lab_config(EXAMPLE)
    assert lab.arena.size_m == (1.83, 1.83)
    cam = lab.camera()
    assert (cam.name, cam.width, cam.height) == ("cam0", 640, 480)
    assert len(cam.calibration["points"]) == 4
    assert [r.name for r in lab.robots] == ["zumo1", "zumo2", "zumo3", "zumo4"]
    assert lab.robot("zumo1").color_rgb == (20, 20, 20)
    assert lab.robot("zumo2").marker_id == 2
    assert lab.zenoh.mode == "client" and lab.zenoh.multicast_scouting is False
    assert lab.service("tracker")["accumulation_ms"] == 100


def write(tmp_path, text):
    p = tmp_path / "lab.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("text,expected", [
    ("[arena]\nsize_m = [1.83]\n", "arena.size_m: expected a pair of positive numbers"),
    ("[arena]\nsize_m = [1.83, -1]\n", "arena.size_m: expected a pair of positive numbers"),
    ("[zenoh]\nmode = 'server'\n", "zenoh.mode: expected one of peer, client, router, got 'server'"),
    ("[zenoh]\nconnect = ['127.0.0.1:7447']\n", "zenoh.connect: expected a list of endpoints"),
    ("[[robots]]\ncolor = 'black'\n", "robots[0].name: expected a string (this key is required)"),
    ("[[robots]]\nname = 'a/b'\n", "robots[0].name: expected a valid name"),
    ("[[robots]]\nname = 'r1'\nmarker_id = 'seven'\n", "robots[0].marker_id: expected an integer"),
    ("[[robots]]\nname = 'r1'\ncolor = 'mauve'\n", "robots[0].color: expected a colour name"),
    ("[[robots]]\nname = 'r1'\n[[robots]]\nname = 'r1'\n", "robots[1].name: expected a name not used by another robot"),
    ("[[robots]]\nname = 'r1'\nmarker_id = 1\n[[robots]]\nname = 'r2'\nmarker_id = 1\n",
     "robots[1].marker_id: expected a marker id not used"),
    ("[[robots]]\nname = 'all'\n", "reserved"),
    ("[[robots]]\nname = 'r1'\ntrack_width_m = 0\n", "robots[0].track_width_m: expected a finite number > 0"),
    ("[[robots]]\nname = 'r1'\nwheels = 3\n", "robots[0]: unknown key(s) wheels"),
    ("[[cameras]]\nname = 'c'\npoints = [{pixel = [0, 0], arena_m = [0, 0]}]\n", "cameras[0].points: expected a list of at least 4"),
    ("[[cameras]]\nname = 'c'\npoints = [{pixel = [0, 0]}, {pixel = [0, 0]}, {pixel = [0, 0]}, {pixel = [0, 0]}]\n",
     "cameras[0].points[0]"),
    ("[[cameras]]\nname = 'c'\nwidth = 'wide'\n", "cameras[0].width: expected an integer"),
    ("[webcam]\nfps = -3\n", "webcam.fps: expected a finite number > 0"),
    ("[cameraz]\n", "unknown key(s) cameraz"),
    ("[arena\n", "not valid TOML"),
])
def test_each_mistake_has_its_own_clear_message(tmp_path, text, expected):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        load_lab_config(p)
    msg = str(exc.value)
    assert msg.startswith(str(p)), msg
    assert expected in msg, msg


def test_missing_file_says_where_to_find_a_template(tmp_path):
    with pytest.raises(ConfigError, match="lab.example.toml"):
        load_lab_config(tmp_path / "nope.toml")


def test_calibration_file_is_relative_to_the_config(tmp_path):
    p = write(tmp_path, "[[cameras]]\nname = 'c'\ncalibration = 'c.json'\n")
    assert load_lab_config(p).camera("c").calibration_file == str(tmp_path / "c.json")
    with pytest.raises(ConfigError, match="no camera named 'x'"):
        load_lab_config(p).camera("x")
