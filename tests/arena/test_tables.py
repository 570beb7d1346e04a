"""The tracks CSV and the truth CSVs of arena.formats.tables: exact bytes written, round trips through
the one reader, and the reader's format errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from arena.formats.tables import (GROUNDTRUTH_CSV_HEADER, TRACK_CSV_HEADER, TRACK_DTYPE, TRUTH_CSV_HEADER,
                                  TRUTH_DTYPE, CsvFormatError, GroundTruthCsvWriter, TrackCsvWriter, TruthCsvWriter,
                                  read_tracks_csv, read_truth_csv, tracks_array, write_tracks_csv, write_truth_csv)
from groundtruth.rgb import Detection
from tracker.objects import TrackedRobot

HOST0 = 1_700_000_000_000_000_000   # ns since the epoch


def _tracks():
    return [TrackedRobot(track_id=1, x=0.123456789, y=1.5, t_us=10_000, vx=0.0123456, vy=-0.5, yaw=-3.14159265,
                         state="confirmed", u=12.345, v=600.0, n_events=321, robot="zumo1"),
            TrackedRobot(track_id=12, x=-0.25, y=0.0, t_us=20_000, state="tentative", robot=None, n_events=0)]


def test_tracks_writer_bytes_and_round_trip_on_both_clocks(tmp_path):
    path = tmp_path / "tracks.csv"
    with path.open("w", newline="") as fh:
        w = TrackCsvWriter(fh)
        assert w.write(_tracks()[:1], sensor_to_host_ns=HOST0 + 7) == 1
        assert w.write(_tracks()[1:]) == 1              # offset unknown: host_ns empty
    assert path.read_bytes() == (
        b"t_us,track_id,robot,x_m,y_m,yaw_rad,vx_mps,vy_mps,u_px,v_px,state,n_events,host_ns\n"
        b"10000,1,zumo1,0.12346,1.50000,-3.14159,0.0123,-0.5000,12.35,600.00,confirmed,321,1700000000010000007\n"
        b"20000,12,,-0.25000,0.00000,,,,,,tentative,0,\n")
    assert path.read_text().splitlines()[0].split(",") == list(TRACK_CSV_HEADER)

    got = read_tracks_csv(path)
    assert got.dtype == TRACK_DTYPE
    assert got["t_us"].tolist() == [10_000, 20_000] and got["track_id"].tolist() == ["1", "12"]
    assert got["robot"].tolist() == ["zumo1", ""] and got["state"].tolist() == ["confirmed", "tentative"]
    assert got["x_m"].tolist() == [0.12346, -0.25] and got["yaw_rad"][0] == -3.14159
    assert got["vx_mps"][0] == 0.0123 and got["u_px"][0] == 12.35 and got["n_events"].tolist() == [321, 0]
    assert np.isnan(got["yaw_rad"][1]) and np.isnan(got["vx_mps"][1]) and np.isnan(got["v_px"][1])

    host = read_tracks_csv(path, clock="host")          # only the row with a host time, on the host clock
    assert host["t_us"].tolist() == [(HOST0 + 10_000 * 1000 + 7) // 1000] and host["track_id"].tolist() == ["1"]


def test_tracks_array_round_trip_through_the_one_writer(tmp_path):
    arr = tracks_array(_tracks())
    assert arr.dtype == TRACK_DTYPE and arr["track_id"].tolist() == ["1", "12"] and arr["robot"].tolist() == ["zumo1", ""]
    assert arr["x_m"][0] == 0.123456789                  # in memory: full precision
    arr["n_events"][1] = -1                               # unknown
    write_tracks_csv(tmp_path / "a.csv", arr)
    lines = (tmp_path / "a.csv").read_text().splitlines()
    assert lines[0].split(",") == list(TRACK_CSV_HEADER)
    assert lines[1] == "10000,1,zumo1,0.12346,1.50000,-3.14159,0.0123,-0.5000,12.35,600.00,confirmed,321,"
    assert lines[2] == "20000,12,,-0.25000,0.00000,,,,,,tentative,,"
    back = read_tracks_csv(tmp_path / "a.csv")
    assert back["n_events"].tolist() == [321, -1]
    rounded = arr.copy()
    for name, digits in (("x_m", 5), ("y_m", 5), ("yaw_rad", 5), ("vx_mps", 4), ("vy_mps", 4), ("u_px", 2),
                         ("v_px", 2)):
        rounded[name] = [float(f"{v:.{digits}f}") for v in arr[name]]   # what the text holds
    for name in TRACK_DTYPE.names:
        np.testing.assert_array_equal(back[name], rounded[name], err_msg=name)   # NaN where NaN
    assert tracks_array([]).dtype == TRACK_DTYPE and len(tracks_array([])) == 0


@pytest.mark.parametrize("cell, message", [("-5", "line 2, column host_ns: -5 is negative"),
                                           ("x", "line 2, column host_ns: cannot read 'x'")])
def test_a_bad_host_time_is_a_format_error(tmp_path, cell, message):
    path = tmp_path / "t.csv"
    path.write_text(",".join(TRACK_CSV_HEADER) + "\n" + f"1000,1,,0.1,0.2,,,,,,confirmed,5,{cell}\n")
    assert len(read_tracks_csv(path)) == 1                 # the sensor clock does not read host_ns
    with pytest.raises(CsvFormatError, match=message):
        read_tracks_csv(path, clock="host")
    with pytest.raises(ValueError, match="clock must be"):
        read_tracks_csv(path, clock="wall")


def test_truth_writer_bytes_and_round_trip(tmp_path):
    sim = np.array([(1000, 1, 0.4575049, 0.1575, 0.0174533, 0.25, -0.00004),
                    (2000, 0, -1.0, 2.0, math.pi, 0.0, 1.23456)],
                   dtype=[("t_us", "<i8"), ("robot", "<i4"), ("x_m", "<f8"), ("y_m", "<f8"),
                          ("yaw_rad", "<f8"), ("vx_mps", "<f8"), ("vy_mps", "<f8")])
    path = tmp_path / "truth.csv"
    with TruthCsvWriter(path, ["black0", "yellow1"]) as w:   # the simulator's rows: robot = index
        w.write(sim[:1])
        w.write(sim[1:])
    assert path.read_bytes() == (b"t_us,robot,x_m,y_m,yaw_rad,vx_mps,vy_mps\n"
                                 b"1000,yellow1,0.45750,0.15750,0.01745,0.2500,-0.0000\n"
                                 b"2000,black0,-1.00000,2.00000,3.14159,0.0000,1.2346\n")
    got = read_truth_csv(path)
    assert got.dtype == TRUTH_DTYPE and got["robot"].tolist() == ["yellow1", "black0"]
    assert got["x_m"].tolist() == [0.4575, -1.0] and got["vy_mps"].tolist() == [-0.0, 1.2346]

    named = got.copy()                                     # a TRUTH_DTYPE array (robot = name), NaN yaw
    named["yaw_rad"][1] = np.nan
    write_truth_csv(tmp_path / "named.csv", named)
    assert (tmp_path / "named.csv").read_text().splitlines() == [
        ",".join(TRUTH_CSV_HEADER), "1000,yellow1,0.45750,0.15750,0.01745,0.2500,-0.0000",
        "2000,black0,-1.00000,2.00000,nan,0.0000,1.2346"]
    back = read_truth_csv(tmp_path / "named.csv")
    for name in TRUTH_DTYPE.names:
        np.testing.assert_array_equal(back[name], named[name], err_msg=name)


def test_webcam_ground_truth_is_a_second_truth_format_with_the_same_reader(tmp_path):
    dets = [Detection(1000, "zumo1", 0.1234567, -0.5, math.nan, 100.125, 50.0, "aruco"),
            Detection(42_000, "zumo2", 1.0, 1.25, 0.5, 3.0, 4.556, "hsv")]
    path = tmp_path / "groundtruth.csv"
    with GroundTruthCsvWriter(path) as w:
        w.write(dets)
    assert path.read_bytes() == (b"t_us,robot,x_m,y_m,yaw_rad,u_px,v_px,detector\r\n"      # csv.writer's lines
                                 b"1000,zumo1,0.12346,-0.50000,nan,100.12,50.00,aruco\r\n"
                                 b"42000,zumo2,1.00000,1.25000,0.50000,3.00,4.56,hsv\r\n")
    assert path.read_text().splitlines()[0].split(",") == list(GROUNDTRUTH_CSV_HEADER)
    got = read_truth_csv(path)
    assert got["t_us"].tolist() == [1000, 42_000] and got["robot"].tolist() == ["zumo1", "zumo2"]
    assert got["x_m"].tolist() == [0.12346, 1.0] and got["y_m"].tolist() == [-0.5, 1.25]
    assert np.isnan(got["yaw_rad"][0]) and got["yaw_rad"][1] == 0.5
    assert np.isnan(got["vx_mps"]).all() and np.isnan(got["vy_mps"]).all()     # the webcam has no velocity


def test_truth_reader_errors_name_the_file_and_line(tmp_path):
    p = tmp_path / "t.csv"
    p.write_text("t_us,robot,x_m\n1,a,0\n")
    with pytest.raises(CsvFormatError, match="header lacks column.s. y_m"):
        read_truth_csv(p)
    p.write_text("t_us,robot,x_m,y_m\n1,a,0,0\n2,,0,0\n")
    with pytest.raises(CsvFormatError, match="line 3: empty robot name"):
        read_truth_csv(p)
    with pytest.raises(CsvFormatError, match="not found"):
        read_truth_csv(tmp_path / "missing.csv")
