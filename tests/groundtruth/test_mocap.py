"""Motion capture as ground truth (groundtruth/mocap.py): frame fit, clock offset, readers.

Synthetic data with a known clock offset and frame (the helpers below are also used by the
end-to-end test of `arena eval` in test_eval_cli.py); recovered within 1 ms and 1 mm.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from arena.formats.tables import TRACK_DTYPE, TRUTH_DTYPE
from groundtruth.mocap import (MissingRosbags, MocapError, Transform2D, align_truth, correlate_speeds,
                               fit_transform, read_pose_bag, read_pose_csv, topic_body_name)

POSE = "geometry_msgs/msg/PoseStamped"


def circles_truth(duration_s: float = 6.0, step_us: int = 2000) -> np.ndarray:
    """Two robots starting at 0.3 s and 0.7 s (speeding up with a 0.15 s time constant) onto
    0.3 m circles at 0.46 m/s, arena frame, at ``step_us``."""
    rows = []
    for k in range(int(duration_s * 1e6 / step_us)):
        t = k * step_us
        for r, (cx, phase, t0) in {"zumo1": (0.6, 0.0, 0.3e6), "zumo2": (1.2, 1.0, 0.7e6)}.items():
            tm = max(0.0, t - t0) * 1e-6
            s = 0.46 * (tm - 0.15 * (1 - math.exp(-tm / 0.15)))
            v = 0.46 * (1 - math.exp(-tm / 0.15))
            a = phase + s / 0.3
            rows.append((t, r, cx + 0.3 * math.cos(a), 0.9 + 0.3 * math.sin(a),
                         math.remainder(a + math.pi / 2, 2 * math.pi), -v * math.sin(a), v * math.cos(a)))
    return np.array(rows, dtype=TRUTH_DTYPE)


def tracks_from_truth(truth: np.ndarray, period_us: int = 10_000, noise_m: float = 0.002, named: bool = True,
                      seed: int = 1) -> np.ndarray:
    """Tracker-like rows: the truth every ``period_us`` per robot plus Gaussian position noise; track
    ids 1, 2, ... per robot (and the robot's name when ``named``)."""
    rng = np.random.default_rng(seed)
    out = []
    names = sorted(set(truth["robot"]))
    for i, name in enumerate(names):
        rows = truth[truth["robot"] == name]
        rows = rows[np.argsort(rows["t_us"])]
        t0 = int(rows["t_us"][0])
        grid = np.arange(t0, int(rows["t_us"][-1]) + 1, period_us)
        x, y = np.interp(grid, rows["t_us"], rows["x_m"]), np.interp(grid, rows["t_us"], rows["y_m"])
        yaw = np.interp(grid, rows["t_us"], np.unwrap(rows["yaw_rad"]))
        for k, t in enumerate(grid):
            out.append((t, str(i + 1), name if named else "", x[k] + rng.normal(0, noise_m),
                        y[k] + rng.normal(0, noise_m), math.remainder(yaw[k], 2 * math.pi), np.nan, np.nan,
                        np.nan, np.nan, "confirmed", 500))
    tracks = np.array(out, dtype=TRACK_DTYPE)
    return tracks[np.argsort(tracks["t_us"], kind="stable")]


def to_mocap(truth: np.ndarray, frame: Transform2D, offset_us: int, rate_hz: float = 120.0,
             noise_m: float = 0.0002, seed: int = 2) -> np.ndarray:
    """``truth`` resampled at ``rate_hz`` on the mocap clock (mocap time + offset = arena time) in
    the mocap frame (arena = frame(mocap)), with a little noise."""
    rng = np.random.default_rng(seed)
    out = []
    c, s = math.cos(-frame.rotation_rad), math.sin(-frame.rotation_rad)
    for name in sorted(set(truth["robot"])):
        rows = truth[truth["robot"] == name]
        rows = rows[np.argsort(rows["t_us"])]
        t_m = np.arange(int(rows["t_us"][0]) - offset_us, int(rows["t_us"][-1]) - offset_us, 1e6 / rate_hz)
        t_m = np.round(t_m).astype(np.int64)
        t_a = (t_m + offset_us).astype(np.float64)
        x = np.interp(t_a, rows["t_us"], rows["x_m"])
        y = np.interp(t_a, rows["t_us"], rows["y_m"])
        yaw = np.interp(t_a, rows["t_us"], np.unwrap(rows["yaw_rad"]))
        dx, dy = (x - frame.tx_m) / frame.scale, (y - frame.ty_m) / frame.scale
        mx = c * dx - s * dy + rng.normal(0, noise_m, len(t_m))
        my = s * dx + c * dy + rng.normal(0, noise_m, len(t_m))
        for k in range(len(t_m)):
            out.append((t_m[k], name, mx[k], my[k], math.remainder(yaw[k] - frame.rotation_rad, 2 * math.pi),
                        np.nan, np.nan))
    m = np.array(out, dtype=TRUTH_DTYPE)
    return m[np.argsort(m["t_us"], kind="stable")]


def write_pose_bag(path: Path, mocap: np.ndarray, topic_of=lambda n: f"/vrpn_client_node/{n}/pose",
                   extra_topics: dict[str, np.ndarray] | None = None) -> Path:
    """``mocap`` rows as a rosbag2 (MCAP storage) of PoseStamped (header stamp = t_us, z = 0.05 m,
    frame_id ``world``), one topic per body, bag time 1 ms after the stamp."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    t = ts.types
    groups = {topic_of(n): mocap[mocap["robot"] == n] for n in sorted(set(mocap["robot"]))}
    groups.update(extra_topics or {})
    items = []
    for topic, rows in groups.items():
        for r in rows:
            ns = int(r["t_us"]) * 1000
            half = float(r["yaw_rad"]) / 2
            msg = t[POSE](
                header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](
                    sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id="world"),
                pose=t["geometry_msgs/msg/Pose"](
                    position=t["geometry_msgs/msg/Point"](x=float(r["x_m"]), y=float(r["y_m"]), z=0.05),
                    orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(half), w=math.cos(half))))
            items.append((ns + 1_000_000, topic, bytes(ts.serialize_cdr(msg, POSE))))
    items.sort(key=lambda it: it[0])
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {topic: w.add_connection(topic, POSE, typestore=ts) for topic in groups}
        for stamp, topic, data in items:
            w.write(conns[topic], stamp, data)
    return path


def _rotation_error_mm(got: dict, want: Transform2D, radius_m: float = 1.0) -> float:
    return abs(math.radians(got["rotation_deg"]) - want.rotation_rad) * radius_m * 1e3


# ----------------------------------------------------------------------------------------------
# the frame fit


@pytest.mark.parametrize("mode, scale", [("rigid", 1.0), ("similarity", 1.02)])
def test_fit_transform_recovers_a_known_frame(mode, scale):
    rng = np.random.default_rng(3)
    src = rng.uniform(-1, 1, (400, 2))
    want = Transform2D(math.radians(30), 0.5, -0.2, scale)
    dst = np.column_stack(want.apply(src[:, 0], src[:, 1])) + rng.normal(0, 0.002, (400, 2))
    got = fit_transform(src, dst, mode)
    assert math.degrees(got.rotation_rad) == pytest.approx(30.0, abs=0.03)
    assert got.tx_m == pytest.approx(0.5, abs=1e-3) and got.ty_m == pytest.approx(-0.2, abs=1e-3)
    assert got.scale == pytest.approx(scale, abs=1e-3)


def test_fit_transform_of_a_mirror_image_is_the_best_rotation():
    """A frame with a flipped axis (a y-down mocap) has no rotation that fits: the fit must still
    be the best proper rotation, not the reflection's angle."""
    rng = np.random.default_rng(4)
    src = rng.uniform(-1, 1, (200, 2)) * [1.0, 0.3]
    dst = src * [1, -1] @ np.array([[0.6, -0.8], [0.8, 0.6]]).T
    got = fit_transform(src, dst, "rigid")
    rms = lambda tf: float(np.sqrt(np.mean(np.sum((np.column_stack(tf.apply(src[:, 0], src[:, 1])) - dst) ** 2, 1))))  # noqa: E731
    best = min(rms(Transform2D(a, *(dst.mean(0) - np.array(Transform2D(a).apply(*src.mean(0)))))) for a in
               np.radians(np.arange(-180, 180, 0.1)))
    assert rms(got) <= best + 1e-6


# ----------------------------------------------------------------------------------------------
# the clock offset


def test_speed_correlation_gives_the_sign_of_the_offset():
    truth = circles_truth(4.0)
    groups = lambda a: [(a["t_us"][a["robot"] == n], a["x_m"][a["robot"] == n], a["y_m"][a["robot"] == n])  # noqa: E731
                        for n in ("zumo1", "zumo2")]
    later = truth.copy()
    later["t_us"] += 250_000                  # the same motion seen 250 ms later on the other clock
    off, r, nxt = correlate_speeds(groups(truth), groups(later))
    assert off == pytest.approx(250_000, abs=5000) and r > 0.99 and nxt < r


@pytest.mark.parametrize("named, mode, scale", [(True, "rigid", 1.0), (False, "rigid", 1.0),
                                                (True, "similarity", 1.02), (False, "similarity", 1.02)])
def test_align_truth_recovers_offset_and_frame(named, mode, scale):
    truth = circles_truth(8.0)
    tracks = tracks_from_truth(truth, named=named)
    frame = Transform2D(math.radians(30), 0.5, -0.2, scale)
    offset_us = 123_400          # mocap time + 123.4 ms = track time
    al = align_truth(tracks, to_mocap(truth, frame, offset_us), time_offset_us=None, align=mode)
    assert al.offset_us == pytest.approx(offset_us, abs=500), al.estimate   # target 1 ms; the coarse peak alone is ~0.8 ms off
    assert al.estimate.stderr_us < 1000 and al.estimate.correlation > 0.9
    f = al.fit.to_dict()
    assert f["pairing"] == ("name" if named else "nearest")
    assert f["translation_m"][0] == pytest.approx(0.5, abs=1e-3) and f["translation_m"][1] == pytest.approx(-0.2, abs=1e-3)
    assert _rotation_error_mm(f, frame) < 1.0 and f["scale"] == pytest.approx(scale, abs=1e-3)
    assert f["rms_mm"] == pytest.approx(2.0 * math.sqrt(2), rel=0.2)     # the tracks' own noise
    assert f["pairs_per_robot"]["zumo1"] > 500 and f["pairs_per_robot"]["zumo2"] > 500
    # the aligned truth is the original truth again (within the mocap noise)
    back = al.truth[al.truth["robot"] == "zumo1"]
    orig = truth[truth["robot"] == "zumo1"]
    x = np.interp(back["t_us"], orig["t_us"], orig["x_m"])
    assert np.max(np.abs(back["x_m"] - x)[50:-50]) < 0.003


def test_align_truth_with_a_huge_given_offset_and_no_frame():
    truth = circles_truth(3.0)
    tracks = tracks_from_truth(truth)
    epoch = 1_700_000_000_000_000                       # mocap stamps on the host's wall clock, µs
    al = align_truth(tracks, to_mocap(truth, Transform2D(), -epoch), time_offset_us=-epoch, align="none")
    assert al.offset_us == -epoch and al.offset_source == "given" and al.estimate is None
    assert al.truth["t_us"].min() < 10_000 and al.fit.rms_m < 0.004


def test_align_truth_without_overlap_is_a_clear_error():
    truth = circles_truth(3.0)
    tracks = tracks_from_truth(truth)
    with pytest.raises(MocapError, match="overlaps"):
        align_truth(tracks, to_mocap(truth, Transform2D(0.5, 0.1, 0.1), -100_000_000), time_offset_us=0.0,
                    align="rigid")


# ----------------------------------------------------------------------------------------------
# readers


def test_pose_csv_headers(tmp_path):
    p = tmp_path / "optitrack.csv"
    p.write_text("t_s,name,x,y,z,qx,qy,qz,qw\n"
                 f"1700000000.123456,Zumo_01,0.1,0.2,0.05,0,0,{math.sin(0.25)},{math.cos(0.25)}\n"
                 "1700000000.133456,Zumo_01,,,,,,,\n")
    gt = read_pose_csv(p)
    assert list(gt["t_us"]) == [1_700_000_000_123_456, 1_700_000_000_133_456]
    assert gt["yaw_rad"][0] == pytest.approx(0.5) and np.isnan(gt["x_m"][1])
    assert list(read_pose_csv(p, {"zumo1": "Zumo_01"})["robot"]) == ["zumo1", "zumo1"]
    q = tmp_path / "vicon.csv"
    q.write_text("T_NS,Body,X_M,Y_M,yaw_deg\n5000000,a,1,2,90\n")
    gt = read_pose_csv(q)
    assert gt["t_us"][0] == 5000 and gt["robot"][0] == "a" and gt["yaw_rad"][0] == pytest.approx(math.pi / 2)
    bad = tmp_path / "bad.csv"
    bad.write_text("time,who,x,y\n0,a,1,2\n")
    with pytest.raises(MocapError, match="needs a time"):
        read_pose_csv(bad)


def test_topic_names():
    assert topic_body_name("/vrpn_client_node/zumo1/pose") == "zumo1"
    assert topic_body_name("/mocap/zumo2") == "zumo2"
    assert topic_body_name("/pose") == "pose"


def test_read_pose_bag_folder_and_mcap_file(tmp_path):
    truth = circles_truth(1.0)
    mocap = to_mocap(truth, Transform2D(0.3, 0.1, 0.2), -1_700_000_000_000_000, noise_m=0.0)
    bag = write_pose_bag(tmp_path / "bag", mocap)
    got = read_pose_bag(bag)
    assert got.topics == {"/vrpn_client_node/zumo1/pose": "zumo1", "/vrpn_client_node/zumo2/pose": "zumo2"}
    assert got.header_stamps == len(mocap) and got.log_stamps == 0
    np.testing.assert_array_equal(np.sort(got.truth["t_us"]), np.sort(mocap["t_us"]))
    one = got.truth[got.truth["robot"] == "zumo1"]
    want = mocap[mocap["robot"] == "zumo1"]
    np.testing.assert_allclose(one["x_m"], want["x_m"], atol=1e-12)
    np.testing.assert_allclose(one["yaw_rad"], want["yaw_rad"], atol=1e-9)
    (mcap_file,) = bag.glob("*.mcap")
    alone = tmp_path / "alone.mcap"
    alone.write_bytes(mcap_file.read_bytes())       # a bare .mcap file, without metadata.yaml
    got2 = read_pose_bag(alone, bodies={"r1": "/vrpn_client_node/zumo1/pose"})
    assert got2.topics == {"/vrpn_client_node/zumo1/pose": "r1"} and set(got2.truth["robot"]) == {"r1"}
    np.testing.assert_array_equal(got2.truth["x_m"], one["x_m"])
    assert set(read_pose_bag(bag, ["*zumo2*"]).truth["robot"]) == {"zumo2"}


def test_read_pose_bag_errors(tmp_path):
    truth = circles_truth(0.5)
    mocap = to_mocap(truth, Transform2D(), 0)
    bag = write_pose_bag(tmp_path / "bag", mocap, extra_topics={"/arena/robots/zumo1/pose": mocap[:5]})
    with pytest.raises(MocapError, match="both name the robot 'zumo1'.*--truth-topic"):
        read_pose_bag(bag)
    with pytest.raises(MocapError, match="no PoseStamped topic /nope"):
        read_pose_bag(bag, bodies={"a": "/nope"})
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(MocapError, match="cannot read"):
        read_pose_bag(junk)


def test_missing_rosbags_is_named(monkeypatch, tmp_path):
    import sys

    monkeypatch.setitem(sys.modules, "rosbags.typesys", None)    # as if the 'ros2' extra were not installed
    with pytest.raises(MissingRosbags, match=r"pip install 'arena-fleet\[ros2\]'"):
        read_pose_bag(tmp_path)
