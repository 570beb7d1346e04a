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


# ----------------------------------------------------------------------------- [services.<role>]


@pytest.mark.parametrize("text,expected", [
    ("[services.sim]\nspeed = 2\n",
     "unknown table [services.sim]; known service tables: [services.edge], [services.tracker], [services.bridge]"),
    ("[services]\ntrackr = {tracker = 'idtrack'}\n", "unknown table [services.trackr]"),
    ("[services.edge]\nslice = 3\n", "services.edge: unknown key(s) slice; known: slice_ms, codec,"),
    ("[services.tracker]\naccumulation = 100\n", "services.tracker: unknown key(s) accumulation; known: tracker,"),
    ("[services.bridge]\ntelemetry = 'logs'\n", "services.bridge: unknown key(s) telemetry; known: telemetry_dir,"),
    ("[services.tracker]\ntracker = 'kalman'\n", "services.tracker.tracker: expected one of fleet, idtrack, got 'kalman'"),
    ("[services.tracker]\naccumulation_ms = '100'\n", "services.tracker.accumulation_ms: expected a finite number > 0, got '100'"),
    ("[services.tracker]\nfleet_size = 0\n", "services.tracker.fleet_size: expected an integer >= 1, got 0"),
    ("[services.edge]\nqueue = 'big'\n", "services.edge.queue: expected an integer >= 1, got 'big'"),
    ("[services.edge]\ncodec = 'gzip'\n", "services.edge.codec: expected one of planes-zstd/1"),
    ("[services.edge]\ndenoise = 'x'\n", "services.edge.denoise: expected an integer > 0 or true or false"),
    ("[services.bridge]\nlow_battery_mv = 4.4\n", "services.bridge.low_battery_mv: expected an integer >= 0, got 4.4"),
    ("[services.bridge]\ngeofence_margin_m = true\n", "services.bridge.geofence_margin_m: expected a finite number >= 0"),
    ("[services.bridge]\nbaudrate = '57600'\n", "services.bridge.baudrate: expected an integer > 0"),
    ("[services.bridge]\ntelemetry_dir = 3\n", "services.bridge.telemetry_dir: expected a string, got 3"),
    ("[services.viewer]\nport = 70000\n", "services.viewer.port: expected an integer in [0, 65535], got 70000"),
    ("[services.recorder]\nkeys = 3\n", "services.recorder.keys: expected a list of strings, got 3"),
    ("[services.groundtruth]\nname = 'web cam'\n", "services.groundtruth.name: expected a name"),
    ("[services]\nedge = 3\n", "services.edge: expected a table of options, got 3"),
])
def test_service_tables_are_checked_when_the_file_is_loaded(tmp_path, text, expected):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        load_lab_config(p)
    msg = str(exc.value)
    assert msg.startswith(f"{p}: "), msg
    assert expected in msg, msg


def test_every_option_of_the_example_labs_is_known_and_typed():
    from arena.config import SERVICE_OPTIONS

    for path in (EXAMPLE, REPO / "deploy" / "docker" / "lab.toml"):
        lab = load_lab_config(path)
        assert set(lab.services) <= set(SERVICE_OPTIONS)
        assert lab.service("tracker") == {"accumulation_ms": 100.0, "tracker": "fleet"}
        assert isinstance(lab.service("edge")["slice_ms"], float)  # `slice_ms = 10` is a float option
        assert isinstance(lab.service("bridge")["telemetry_dir"], str)
        assert lab.service("viewer") == {}


def test_service_options_fill_unset_flags_flags_win_then_the_lab_then_defaults(tmp_path):
    import argparse

    from arena.config import apply_service_options

    p = write(tmp_path, "[services.tracker]\ntracker = 'idtrack'\naccumulation_ms = 60\nnames_from_groundtruth = false\n"
                        "[services.bridge]\ngeofence_margin_m = 0\nbaudrate = 115200\n"
                        "[services.recorder]\nkeys = 'arena/robots/*'\n")
    lab = load_lab_config(p)
    args = argparse.Namespace(tracker=None, accumulation_ms=20.0, detector=None, names_from_groundtruth=None)
    origin = apply_service_options(args, lab, "tracker")
    assert (args.tracker, args.accumulation_ms, args.detector, args.names_from_groundtruth) == ("idtrack", 20.0,
                                                                                                 "default", False)
    assert origin["tracker"] == "lab" and origin["accumulation_ms"] == "flag" and origin["detector"] == "default"
    assert args.state_max_age == 600.0  # the option state_max_age_s fills the flag --state-max-age
    # the bridge's options fill its flags' names (--geofence-margin, --baud, --log-dir); a 0 is a value
    args = argparse.Namespace(geofence_margin=None, baud=None, log_dir=None)
    apply_service_options(args, lab, "bridge")
    assert (args.geofence_margin, args.baud, args.log_dir) == (0.0, 115200, "bridge_logs")
    args = argparse.Namespace(keys=None, queue=None)
    apply_service_options(args, lab, "recorder")
    assert (args.keys, args.queue) == (["arena/robots/*"], 10_000)
    args = argparse.Namespace(host=None, port=None, accumulate_ms=None, rate=None)
    apply_service_options(args, None, "viewer")  # no lab file: the defaults
    assert (args.host, args.port, args.accumulate_ms, args.rate) == ("127.0.0.1", 8080, 100.0, 10.0)


def test_the_example_documents_every_service_option_and_its_commented_options_load(tmp_path):
    """The option list in deploy/lab.example.toml is SERVICE_OPTIONS, and every commented-out
    option there is valid when uncommented."""
    import re

    from arena.config import SERVICE_OPTIONS

    text = EXAMPLE.read_text()
    listed = dict(re.findall(r"^#\s{3}(\w+):\s+(.*)$", text, re.M))
    more = re.findall(r"^#\s{16,}(\w[\w ]*)$", text, re.M)  # continuation lines of the list
    assert set(listed) == set(SERVICE_OPTIONS)
    assert set(" ".join(listed.values()).split() + " ".join(more).split()) == {
        k for opts in SERVICE_OPTIONS.values() for k in opts}
    tables = text[text.index("\n[services.edge]"):]
    uncommented = re.sub(r"^# (\[services\.\w+\]|\w+ = .*)$", r"\1", tables, flags=re.M)
    assert uncommented != tables
    p = write(tmp_path, text[:text.index("\n[services.edge]")] + uncommented)
    lab = load_lab_config(p)
    assert lab.service("edge")["denoise"] is True and lab.service("viewer") == {"port": 8080}
    assert lab.service("bridge")["low_battery_mv"] == 4400


def test_a_huge_toml_integer_is_a_config_error_not_an_overflow():
    """TOML integers have any size; one too big for a float is refused like any bad number."""
    from arena.config import ConfigError, parse_lab_config

    for doc in ({"arena": {"size_m": [10**400, 1]}},):
        with pytest.raises(ConfigError, match="size_m"):
            parse_lab_config(doc)
