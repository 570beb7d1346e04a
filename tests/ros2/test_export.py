"""`arena export RUN --rosbag OUT`: a run folder written with the project's own writers, exported,
and read back with rosbags' own Reader and CDR deserializer."""

from __future__ import annotations

import argparse
import io
import math
import subprocess
import sys
from importlib.metadata import entry_points

import numpy as np
import pytest
from mcap.reader import make_reader

pytest.importorskip("rosbags")
from rosbags.rosbag2 import Reader  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from arena.messages import Track  # noqa: E402
from arena.formats.tables import TRUTH_DTYPE, TrackCsvWriter, read_tracks_csv, write_truth_csv  # noqa: E402
from recorder.mcapio import RunWriter  # noqa: E402
from ros2.bag import ExportError, export_run  # noqa: E402
from ros2.cdr import Serializer  # noqa: E402
from ros2.cli import register_export  # noqa: E402
from ros2.convert import (bridge_key, entity_name, quaternion_from_yaw, rmw_zenoh_key, ros_token,  # noqa: E402
                          yaw_from_quaternion)
from tests.conftest import arena_cmd  # noqa: E402
from tracker.objects import TrackedRobot  # noqa: E402

TS = get_typestore(Stores.ROS2_HUMBLE)

# two tracker updates of two robots; track 3 is not identified yet; zumo-2 has a '-' (not ROS);
# one row without a heading
TRACKS = [
    TrackedRobot(track_id=1, x=0.50, y=0.25, t_us=1_000_000, yaw=0.3, robot="zumo1", n_events=900),
    TrackedRobot(track_id=2, x=1.10, y=0.40, t_us=1_000_000, yaw=-2.5, robot="zumo-2", n_events=800),
    TrackedRobot(track_id=3, x=0.80, y=0.90, t_us=1_000_000, robot=None, n_events=300),  # yaw unknown
    TrackedRobot(track_id=1, x=0.51, y=0.26, t_us=1_010_000, yaw=0.31, robot="zumo1", n_events=910),
    TrackedRobot(track_id=2, x=1.09, y=0.41, t_us=1_010_000, yaw=3.1, robot="zumo-2", n_events=810),
]


def _truth(rows) -> np.ndarray:
    a = np.zeros(len(rows), dtype=TRUTH_DTYPE)
    for i, (t, r, x, y, yaw) in enumerate(rows):
        a[i] = (t, r, x, y, yaw, 0.0, 0.0)
    return a


def make_run(folder, tracks=TRACKS, truth=True):
    folder.mkdir(parents=True, exist_ok=True)
    buf = io.StringIO()
    TrackCsvWriter(buf).write(tracks)
    (folder / "tracks.csv").write_text(buf.getvalue())
    if truth:
        write_truth_csv(folder / "truth.csv", _truth([(1_000_000, "zumo1", 0.501, 0.249, 0.29),
                                                      (1_005_000, "zumo1", 0.505, 0.255, 0.30),
                                                      (1_000_000, "zumo-2", 1.101, 0.399, -2.49)]))
        write_truth_csv(folder / "groundtruth.csv", _truth([(1_000_100, "zumo1", 0.502, 0.248, 0.28),
                                                            (1_040_000, "zumo1", math.nan, math.nan, math.nan)]))
    return folder


def read_bag(path):
    """{topic: [(bag timestamp, message)]} and {topic: msgtype}, read with rosbags' Reader."""
    out, types = {}, {}
    with Reader(path) as r:
        for c in r.connections:
            types[c.topic] = c.msgtype
        for c, t, raw in r.messages():
            out.setdefault(c.topic, []).append((t, TS.deserialize_cdr(raw, c.msgtype)))
    return out, types


def _stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def test_export_round_trip_poses_equal_tracks_csv(tmp_path):
    run = make_run(tmp_path / "run")
    res = export_run(run, tmp_path / "bag", Serializer())
    bag, types = read_bag(tmp_path / "bag")
    assert (tmp_path / "bag" / "metadata.yaml").is_file() and list((tmp_path / "bag").glob("*.mcap"))
    assert set(bag) == {"/arena/robots/zumo1/pose", "/arena/robots/zumo_2/pose", "/arena/robots/track_3/pose",
                        "/tf", "/arena/groundtruth/zumo1/pose", "/arena/sim/truth/zumo1/pose",
                        "/arena/sim/truth/zumo_2/pose"}
    assert types["/tf"] == "tf2_msgs/msg/TFMessage"
    assert all(types[t] == "geometry_msgs/msg/PoseStamped" for t in bag if t != "/tf")
    assert res.track_rows == 5 and res.unknown_yaw == 1 and res.skipped_truth_rows == 1

    # every tracks.csv row (read with the scorer's own reader) is one PoseStamped, in file order per topic
    rows = read_tracks_csv(run / "tracks.csv")
    assert len(rows) == 5
    seen = {t: 0 for t in bag}
    for r in rows:
        topic = f"/arena/robots/{entity_name(str(r['robot']), str(r['track_id']))}/pose"
        t_bag, m = bag[topic][seen[topic]]
        seen[topic] += 1
        assert t_bag == _stamp_ns(m.header) == int(r["t_us"]) * 1000
        assert m.header.frame_id == "arena"
        assert (m.pose.position.x, m.pose.position.y, m.pose.position.z) == (r["x_m"], r["y_m"], 0.0)
        q = m.pose.orientation
        if math.isnan(r["yaw_rad"]):
            assert all(math.isnan(v) for v in (q.x, q.y, q.z, q.w))
        else:
            assert (q.x, q.y) == (0.0, 0.0)
            assert q.z == pytest.approx(math.sin(r["yaw_rad"] / 2), abs=1e-12)
            assert q.w == pytest.approx(math.cos(r["yaw_rad"] / 2), abs=1e-12)
            assert yaw_from_quaternion(q.x, q.y, q.z, q.w) == pytest.approx(r["yaw_rad"], abs=1e-12)
    assert sum(seen[t] for t in seen if t.startswith("/arena/robots/")) == 5

    # /tf: one TFMessage per tracker update, arena -> robot, only for poses with a heading
    tf = bag["/tf"]
    assert [t for t, _ in tf] == [1_000_000_000, 1_010_000_000]
    first = {tr.child_frame_id: tr for tr in tf[0][1].transforms}
    assert set(first) == {"zumo1", "zumo_2"}            # track_3 has no heading: no transform
    z1 = first["zumo1"]
    assert z1.header.frame_id == "arena" and _stamp_ns(z1.header) == 1_000_000_000
    assert (z1.transform.translation.x, z1.transform.translation.y) == (0.5, 0.25)
    assert yaw_from_quaternion(z1.transform.rotation.x, z1.transform.rotation.y, z1.transform.rotation.z,
                               z1.transform.rotation.w) == pytest.approx(0.3)

    # ground truth: the webcam's (without its unseen row) and the simulator's
    gt = bag["/arena/groundtruth/zumo1/pose"]
    assert [(t, m.pose.position.x, m.pose.position.y) for t, m in gt] == [(1_000_100_000, 0.502, 0.248)]
    sim = bag["/arena/sim/truth/zumo1/pose"]
    assert [(t, m.pose.position.x) for t, m in sim] == [(1_000_000_000, 0.501), (1_005_000_000, 0.505)]
    assert yaw_from_quaternion(*(getattr(sim[1][1].pose.orientation, k) for k in "xyzw")) == pytest.approx(0.30)
    # the MCAP file itself holds the messages in stamp order (read in file order with the mcap package)
    [mcap_file] = (tmp_path / "bag").glob("*.mcap")
    with mcap_file.open("rb") as fh:
        stamps = [m.log_time for _, _, m in make_reader(fh).iter_messages(log_time_order=False)]
    assert stamps == sorted(stamps) and len(stamps) == res.total == 5 + 2 + 1 + 3   # poses, /tf, webcam, simulator


def test_stamps_wall_shift_by_the_offset_seen_in_the_recording(tmp_path):
    run = make_run(tmp_path / "run", truth=False)
    offset = 1_700_000_000_000_000_000
    with RunWriter(run / "arena.mcap") as w:   # the recorder's own writer, as arena demo records
        for i, (delay_ns, stamp_us) in enumerate([(5_000_000, 1_000_000), (2_000_000, 1_010_000), (9_000_000, 1_020_000)]):
            tr = Track(track_id=1, robot="zumo1", stamp_us=stamp_us, x=0.5, y=0.25, yaw=0.3,
                       tracker_publish_ns=offset + stamp_us * 1000 + delay_ns)
            w.add("arena/robots/zumo1", tr.encode(), offset + stamp_us * 1000 + delay_ns + 100)
    res = export_run(run, tmp_path / "bag", Serializer(), stamps="wall")
    assert res.offset_ns == offset + 2_000_000        # the least delayed track
    bag, _ = read_bag(tmp_path / "bag")
    t, m = bag["/arena/robots/zumo1/pose"][0]
    assert t == _stamp_ns(m.header) == 1_000_000 * 1000 + offset + 2_000_000


def _export(argv) -> int:
    p = argparse.ArgumentParser(prog="arena")
    register_export(p.add_subparsers(dest="command"))
    args = p.parse_args(["export", *argv])
    return args.func(args)


def test_cli_errors_are_one_line_with_exit_2(tmp_path, capsys):
    # not a run folder
    (tmp_path / "empty").mkdir()
    assert _export([str(tmp_path / "empty"), "--rosbag", str(tmp_path / "b0")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a run folder (no tracks.csv)" in err[0]
    assert not (tmp_path / "b0").exists()
    # no track at all (only the header)
    make_run(tmp_path / "norows", tracks=[])
    assert _export([str(tmp_path / "norows"), "--rosbag", str(tmp_path / "b1")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has no track" in err[0] and not (tmp_path / "b1").exists()
    # OUT exists: refused, then replaced with --force
    run = make_run(tmp_path / "run")
    assert _export([str(run), "--rosbag", str(tmp_path / "bag")]) == 0
    assert "wrote" in capsys.readouterr().out
    assert _export([str(run), "--rosbag", str(tmp_path / "bag")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists" in err[0] and "--force" in err[0]
    assert _export([str(run), "--rosbag", str(tmp_path / "bag"), "--force"]) == 0
    capsys.readouterr()
    assert len(read_bag(tmp_path / "bag")[0]["/arena/robots/zumo1/pose"]) == 2
    # --force never deletes a folder that is not a bag (the run folder, say)
    assert _export([str(run), "--rosbag", str(run), "--force"]) == 2
    assert "holds the run folder" in capsys.readouterr().err
    (tmp_path / "notabag").mkdir()
    (tmp_path / "notabag" / "keep.txt").write_text("x")
    assert _export([str(run), "--rosbag", str(tmp_path / "notabag"), "--force"]) == 2
    assert "not a rosbag2" in capsys.readouterr().err and (tmp_path / "notabag" / "keep.txt").exists()
    assert _export([str(run), "--rosbag", str(run / "tracks.csv"), "--force"]) == 2
    assert "is a file" in capsys.readouterr().err and (run / "tracks.csv").stat().st_size > 0
    # two robots that would share one ROS 2 name
    clash = make_run(tmp_path / "clash", truth=False,
                     tracks=[TrackedRobot(track_id=1, x=0.1, y=0.1, t_us=10, yaw=0.0, robot="zumo-1"),
                             TrackedRobot(track_id=2, x=0.2, y=0.2, t_us=10, yaw=0.0, robot="zumo_1")])
    assert _export([str(clash), "--rosbag", str(tmp_path / "b3")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "both become the ROS 2 name 'zumo_1'" in err[0] and not (tmp_path / "b3").exists()
    # a bad value names file, line and column
    bad = make_run(tmp_path / "bad", truth=False)
    (bad / "tracks.csv").write_text("t_us,track_id,robot,x_m,y_m\n1000,1,zumo1,abc,0.2\n")
    assert _export([str(bad), "--rosbag", str(tmp_path / "b2")]) == 2
    err = capsys.readouterr().err.strip()
    assert "line 2, column x_m" in err and not (tmp_path / "b2").exists()
    # a stamp a ROS 2 time cannot hold
    (bad / "tracks.csv").write_text("t_us,track_id,robot,x_m,y_m\n-5,1,zumo1,0.1,0.2\n")
    assert _export([str(bad), "--rosbag", str(tmp_path / "b4")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "before 0" in err[0] and not (tmp_path / "b4").exists()


def test_missing_rosbags_prints_the_install_line(tmp_path, capsys, monkeypatch):
    run = make_run(tmp_path / "run")
    for mod in [m for m in sys.modules if m == "rosbags" or m.startswith("rosbags.")]:
        monkeypatch.delitem(sys.modules, mod)
    monkeypatch.setitem(sys.modules, "rosbags", None)       # import rosbags -> ImportError
    assert _export([str(run), "--rosbag", str(tmp_path / "bag")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install 'arena-fleet[ros2]'" in err[0]
    assert not (tmp_path / "bag").exists()


def test_names_and_keys():
    assert ros_token("zumo1") == "zumo1"
    assert ros_token("zumo-2.a") == "zumo_2_a"
    assert ros_token("a--b_") == "a_b"
    assert ros_token("7up") == "robot_7up"
    assert entity_name("", 4) == "track_4" and entity_name(None, "12") == "track_12"
    with pytest.raises(ValueError):
        ros_token("--")
    assert quaternion_from_yaw(math.pi) == pytest.approx((0.0, 0.0, 1.0, 0.0), abs=1e-15)
    assert bridge_key("/arena/robots/zumo1/pose") == "arena/robots/zumo1/pose"
    assert bridge_key("/tf", "/lab") == "lab/tf"
    assert (rmw_zenoh_key("/arena/robots/zumo1/pose", "geometry_msgs/msg/PoseStamped", "RIHS01_ab", 3)
            == "3/arena/robots/zumo1/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_ab")


def test_arena_export_command(tmp_path):
    """The real `arena export` command, once pyproject.toml declares its entry point."""
    if "export" not in {e.name for e in entry_points(group="arena.commands")}:
        pytest.skip('the entry point export = "ros2.cli:register_export" is not declared in pyproject.toml yet')
    run = make_run(tmp_path / "run")
    out = subprocess.run(arena_cmd("export", str(run), "--rosbag", str(tmp_path / "bag")),
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert len(read_bag(tmp_path / "bag")[0]["/arena/robots/zumo_2/pose"]) == 2
    again = subprocess.run(arena_cmd("export", str(run), "--rosbag", str(tmp_path / "bag")),
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 2 and len(again.stderr.strip().splitlines()) == 1
