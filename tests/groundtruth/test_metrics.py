"""Metric definitions of groundtruth.metrics on hand-built cases, and agreement with independent
implementations (motmetrics for CLEAR MOT and IDF1, TrackEval for HOTA) on random scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from arena.formats.tables import TRACK_DTYPE, TRUTH_DTYPE
from groundtruth.metrics import a_ratio, align, evaluate, n_avg_clusters

FRAME_US = 10_000


def truth_of(paths: dict[str, list[tuple]], moving=True) -> np.ndarray:
    """paths: robot -> [(t_us, x, y[, yaw])]; vx set so robots count from the start if moving."""
    rows = []
    for r, pts in paths.items():
        for p in pts:
            yaw = p[3] if len(p) > 3 else math.nan
            rows.append((p[0], r, p[1], p[2], yaw, 0.3 if moving else 0.0, 0.0))
    return np.array(rows, dtype=TRUTH_DTYPE)


def tracks_of(rows: list[tuple]) -> np.ndarray:
    """rows: (t_us, track_id, x, y[, yaw[, state]])."""
    out = []
    for r in rows:
        yaw = r[4] if len(r) > 4 else math.nan
        state = r[5] if len(r) > 5 else "confirmed"
        out.append((r[0], str(r[1]), "", r[2], r[3], yaw, math.nan, math.nan, math.nan, math.nan,
                    state, 100))
    return np.array(out, dtype=TRACK_DTYPE)


def straight(robot_y: dict[str, float], n=10, speed=0.3):
    """Robots moving along +x at constant y, sampled at every frame time."""
    return {r: [(k * FRAME_US, 0.2 + speed * k * FRAME_US * 1e-6, y, 0.0) for k in range(n)]
            for r, y in robot_y.items()}


def on_truth(paths, ids: dict[str, str], skip=(), dx=0.0):
    rows = []
    for r, pts in paths.items():
        for k, p in enumerate(pts):
            if (r, k) in skip:
                continue
            rows.append((p[0], ids[r], p[1] + dx, p[2], p[3]))
    return rows


def test_perfect_tracking_scores_one():
    paths = straight({"a": 0.5, "b": 1.0})
    s = evaluate(tracks_of(on_truth(paths, {"a": "1", "b": "2"})), truth_of(paths))
    assert (s.precision, s.recall, s.mota, s.idf1, s.hota) == (1.0, 1.0, 1.0, 1.0, 1.0)
    assert s.mae_cm == pytest.approx(0.0, abs=1e-9) and s.id_switches == 0
    assert s.n_frames == 10 and s.n_gt == 20 and s.n_tp == 20
    assert s.per_robot["a"].main_track == "1" and s.per_robot["b"].main_track == "2"


def test_a_miss_is_a_false_negative_and_a_fragmentation():
    paths = straight({"a": 0.5, "b": 1.0})
    s = evaluate(tracks_of(on_truth(paths, {"a": "1", "b": "2"}, skip={("b", 5)})), truth_of(paths))
    assert (s.n_tp, s.n_fn, s.n_fp) == (19, 1, 0)
    assert s.recall == pytest.approx(19 / 20) and s.precision == 1.0
    assert s.mota == pytest.approx(1 - 1 / 20)
    assert s.fragmentations == 1 and s.per_robot["b"].fragmentations == 1
    assert s.per_robot["a"].fragmentations == 0 and s.per_robot["b"].n_fn == 1
    assert s.idf1 == pytest.approx(2 * 19 / (20 + 19))


def test_a_false_positive():
    paths = straight({"a": 0.5, "b": 1.0})
    rows = on_truth(paths, {"a": "1", "b": "2"}) + [(3 * FRAME_US, "9", 1.5, 1.5, 0.0)]
    s = evaluate(tracks_of(rows), truth_of(paths))
    assert (s.n_tp, s.n_fn, s.n_fp) == (20, 0, 1)
    assert s.precision == pytest.approx(20 / 21) and s.recall == 1.0
    assert s.mota == pytest.approx(1 - 1 / 20)
    assert s.idf1 == pytest.approx(2 * 20 / (20 + 21))


def test_an_id_switch():
    paths = straight({"a": 0.5})
    rows = [(t, "1" if k < 5 else "3", x, y, yaw) for k, (t, x, y, yaw) in enumerate(paths["a"])]
    s = evaluate(tracks_of(rows), truth_of(paths))
    assert s.id_switches == 1 and s.per_robot["a"].id_switches == 1
    assert s.mota == pytest.approx(1 - 1 / 10)
    assert s.idf1 == pytest.approx(0.5)
    # HOTA: DetA = 1, AssA = 0.5 -> sqrt(0.5)
    assert s.deta == pytest.approx(1.0) and s.assa == pytest.approx(0.5)
    assert s.hota == pytest.approx(math.sqrt(0.5))


def test_a_swap_counts_two_switches():
    paths = straight({"a": 0.5, "b": 0.8})
    rows = []
    for k in range(10):
        ia, ib = ("1", "2") if k < 5 else ("2", "1")
        rows.append((k * FRAME_US, ia, *paths["a"][k][1:]))
        rows.append((k * FRAME_US, ib, *paths["b"][k][1:]))
    s = evaluate(tracks_of(rows), truth_of(paths))
    assert s.id_switches == 2 and s.n_tp == 20
    assert s.mota == pytest.approx(1 - 2 / 20)
    assert s.idf1 == pytest.approx(0.5)


def test_gate_edge_is_inclusive():
    truth = truth_of({"a": [(0, 0.0, 0.5), (FRAME_US, 0.0, 0.5)]})
    at_gate = evaluate(tracks_of([(0, "1", 0.1, 0.5), (FRAME_US, "1", 0.1, 0.5)]), truth)
    assert at_gate.n_tp == 2 and at_gate.mae_cm == pytest.approx(10.0)
    beyond = evaluate(tracks_of([(0, "1", 0.1001, 0.5), (FRAME_US, "1", 0.1001, 0.5)]), truth)
    assert (beyond.n_tp, beyond.n_fp, beyond.n_fn) == (0, 2, 2) and beyond.mota == pytest.approx(-1.0)
    wider = evaluate(tracks_of([(0, "1", 0.1001, 0.5), (FRAME_US, "1", 0.1001, 0.5)]), truth, gate_m=0.2)
    assert wider.n_tp == 2


def test_previous_match_is_kept_while_inside_the_gate():
    # track 1 follows robot a 6 cm off; track 2 appears 1 cm off at frame 2. Hungarian alone would
    # switch to track 2; CLEAR MOT keeps track 1 (no switch) and track 2 is a false positive.
    truth = truth_of({"a": [(k * FRAME_US, 0.5, 0.5) for k in range(4)]})
    rows = [(k * FRAME_US, "1", 0.56, 0.5) for k in range(4)] + \
           [(k * FRAME_US, "2", 0.51, 0.5) for k in (2, 3)]
    s = evaluate(tracks_of(rows), truth)
    assert s.id_switches == 0 and s.n_fp == 2 and s.n_tp == 4
    assert s.mae_cm == pytest.approx(6.0)


def test_robot_counts_only_once_it_has_moved():
    # stands still for frames 0-4 (a track sits on it), then moves
    pts = [(k * FRAME_US, 0.5 + (0.0 if k < 5 else 0.02 * (k - 4)), 0.5) for k in range(10)]
    truth = truth_of({"a": pts}, moving=False)
    tracks = tracks_of([(t, "1", x, y) for t, x, y in pts])
    s = evaluate(tracks, truth)
    # displacement exceeds 1 cm at k = 5 (2 cm): frames 5..9 count
    assert s.n_gt == 5 and s.n_tp == 5 and s.n_fp == 0 and s.n_ignored == 5
    s_all = evaluate(tracks, truth, moved_only=False)
    assert s_all.n_gt == 10 and s_all.n_tp == 10 and s_all.n_ignored == 0


def test_track_on_a_robot_that_never_moves_is_neither_tp_nor_fp():
    still = [(k * FRAME_US, 1.0, 1.0) for k in range(10)]
    moving = straight({"b": 0.5})["b"]
    truth = np.concatenate([truth_of({"a": still}, moving=False), truth_of({"b": moving})])
    rows = [(t, "1", x, y) for t, x, y in still] + [(p[0], "2", p[1], p[2]) for p in moving]
    s = evaluate(tracks_of(rows), truth)
    assert (s.n_gt, s.n_tp, s.n_fp, s.n_ignored) == (10, 10, 0, 10)
    assert s.per_robot["a"].n_gt == 0


def test_heading_error_is_circular():
    truth = truth_of({"a": [(0, 0.5, 0.5, math.radians(179)), (FRAME_US, 0.5, 0.5, math.radians(179))]})
    tracks = tracks_of([(0, "1", 0.5, 0.5, math.radians(-179)), (FRAME_US, "1", 0.5, 0.5, math.nan)])
    s = evaluate(tracks, truth)
    assert s.heading_mae_deg == pytest.approx(2.0) and s.n_heading == 1


def test_truth_is_interpolated_at_track_times_linear_and_circular():
    truth = truth_of({"a": [(0, 0.0, 0.0, math.radians(170)), (20_000, 0.2, 0.0, math.radians(-170))]})
    tracks = tracks_of([(10_000, "1", 0.1, 0.0, math.radians(180))])
    s = evaluate(tracks, truth)
    assert s.n_tp == 1 and s.mae_cm == pytest.approx(0.0, abs=1e-9)
    assert s.heading_mae_deg == pytest.approx(0.0, abs=1e-6)


def test_silent_tracker_is_charged_with_misses():
    paths = straight({"a": 0.5}, n=30)
    rows = [r for k, r in enumerate(on_truth(paths, {"a": "1"})) if not 10 <= k < 20]
    s = evaluate(tracks_of(rows), truth_of(paths))
    assert s.n_frames == 30 and s.n_fn == 10 and s.recall == pytest.approx(20 / 30)


def test_no_tracks_at_all_is_all_misses():
    paths = straight({"a": 0.5})
    s = evaluate(tracks_of([]), truth_of(paths))
    assert s.n_gt == 10 and s.recall == 0.0 and s.mota == 0.0 and s.idf1 == 0.0


def test_tentative_tracks_are_excluded_by_default():
    paths = straight({"a": 0.5})
    rows = on_truth(paths, {"a": "1"}) + [(FRAME_US, "7", 1.5, 1.5, 0.0, "tentative")]
    assert evaluate(tracks_of(rows), truth_of(paths)).n_fp == 0
    assert evaluate(tracks_of(rows), truth_of(paths), exclude_states=()).n_fp == 1


def test_rows_within_merge_tolerance_form_one_frame():
    paths = straight({"a": 0.5, "b": 1.0})
    rows = on_truth(paths, {"a": "1", "b": "2"})
    rows = [(t + (300 if tid == "2" else 0), tid, x, y, yaw) for t, tid, x, y, yaw in rows]
    s = evaluate(tracks_of(rows), truth_of(paths))
    assert s.n_frames == 10 and s.n_tp == 20 and s.n_fn == 0


def test_frames_outside_truth_are_dropped():
    paths = straight({"a": 0.5})
    rows = on_truth(paths, {"a": "1"}) + [(20 * FRAME_US, "1", 1.0, 0.5, 0.0)]
    s = evaluate(tracks_of(rows), truth_of(paths))
    assert s.n_frames_dropped >= 1 and s.n_fp == 0


def test_bad_gate_is_rejected():
    with pytest.raises(ValueError, match="gate"):
        evaluate(tracks_of([]), truth_of(straight({"a": 0.5})), gate_m=0)


def test_paper_clustering_metrics():
    square = np.array([[u, v] for u in range(10) for v in range(10)])  # 10x10 px bounding box
    windows = [[square], [square, square + 50], []]
    assert n_avg_clusters(windows, 1) == pytest.approx(1.0)
    assert n_avg_clusters([1, 2, 3], 2) == pytest.approx(1.0)
    assert a_ratio(windows, 1, 100.0) == pytest.approx((1 + 2 + 0) / 3)
    assert a_ratio([[square[:50]]], 1, 100.0) == pytest.approx(0.5)  # 5 x 10 px
    with pytest.raises(ValueError):
        n_avg_clusters(windows, 0)


# ---------------------------------------------------------------------------------------------
# Agreement with independent implementations on random scenes


def random_scene(seed: int, n_robots=4, n_frames=150):
    """Random walks with noisy, dropped, switched and false tracks; truth sampled at frame times."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0.2, 1.6, size=(n_robots, 2))
    robots = [f"r{i}" for i in range(n_robots)]
    ids = [str(i + 1) for i in range(n_robots)]
    next_id = n_robots + 1
    truth_rows, track_rows = [], []
    for k in range(n_frames):
        t = k * FRAME_US
        pos += rng.normal(0, 0.01, size=pos.shape)
        for i, r in enumerate(robots):
            truth_rows.append((t, r, pos[i, 0], pos[i, 1], 0.0, 0.3, 0.0))
            u = rng.random()
            if u < 0.02:  # new id
                ids[i], next_id = str(next_id), next_id + 1
            elif u < 0.04:  # swap with another robot
                j = int(rng.integers(n_robots))
                ids[i], ids[j] = ids[j], ids[i]
            if rng.random() < 0.08:
                continue  # miss
            err = rng.normal(0, 0.04, size=2)
            track_rows.append((t, ids[i], pos[i, 0] + err[0], pos[i, 1] + err[1]))
        for _ in range(rng.poisson(0.15)):
            track_rows.append((t, str(900 + int(rng.integers(5))), *rng.uniform(0, 1.83, 2)))
    # one track id used twice in a frame would be a tracker bug: keep the first
    seen, rows = set(), []
    for r in track_rows:
        if (r[0], r[1]) not in seen:
            seen.add((r[0], r[1]))
            rows.append(r)
    return tracks_of(rows), np.array(truth_rows, dtype=TRUTH_DTYPE)


def motmetrics_summary(tracks, truth, gate):
    """motmetrics on distances computed here, straight from the arrays (truth at frame times)."""
    np.asfarray = getattr(np, "asfarray", lambda a, dtype=float: np.asarray(a, dtype=dtype))  # numpy 2
    mm = pytest.importorskip("motmetrics")
    acc = mm.MOTAccumulator(auto_id=False)
    gid = {r: i for i, r in enumerate(np.unique(truth["robot"]))}  # integer ids: pandas 3 needs them
    hid = {h: 1000 + i for i, h in enumerate(np.unique(tracks["track_id"]))}
    for k, t in enumerate(np.unique(np.concatenate([tracks["t_us"], truth["t_us"]]))):
        g = truth[truth["t_us"] == t]
        h = tracks[tracks["t_us"] == t]
        d = np.hypot(g["x_m"][:, None] - h["x_m"][None, :], g["y_m"][:, None] - h["y_m"][None, :])
        d[d > gate] = np.nan
        acc.update([gid[r] for r in g["robot"]], [hid[i] for i in h["track_id"]], d, frameid=k)
    mh = mm.metrics.create()
    return mh.compute(acc, metrics=["mota", "idf1", "num_switches", "num_false_positives",
                                    "num_misses", "precision", "recall"], name="x").iloc[0]


@pytest.mark.parametrize("seed", range(6))
def test_clear_mot_and_idf1_agree_with_motmetrics(seed):
    tracks, truth = random_scene(seed)
    ours = evaluate(tracks, truth, gate_m=0.10, moved_only=False)
    ref = motmetrics_summary(tracks, truth, 0.10)
    assert ours.n_fp == ref["num_false_positives"] and ours.n_fn == ref["num_misses"]
    assert ours.id_switches == ref["num_switches"]
    assert round(ours.mota, 4) == round(float(ref["mota"]), 4)
    assert round(ours.idf1, 4) == round(float(ref["idf1"]), 4)
    assert round(ours.precision, 4) == round(float(ref["precision"]), 4)
    assert ours.id_switches > 0 and ours.n_fp > 0  # the scene exercises the rules


@pytest.mark.parametrize("seed", range(3))
def test_hota_agrees_with_trackeval(seed):
    te = pytest.importorskip("trackeval.metrics", reason="TrackEval not installed")
    tracks, truth = random_scene(seed)
    al = align(tracks, truth, 0.10, moved_only=False)
    ours = evaluate(tracks, truth, gate_m=0.10, moved_only=False)
    # TrackEval on similarities computed here from the frames' robots and tracks
    data = {"num_gt_ids": len(al.robots), "num_tracker_ids": len(al.track_ids),
            "gt_ids": [], "tracker_ids": [], "similarity_scores": []}
    for fr in al.frames:
        d = np.hypot(fr.gt_xy[:, None, 0] - fr.trk_xy[None, :, 0], fr.gt_xy[:, None, 1] - fr.trk_xy[None, :, 1])
        data["gt_ids"].append(fr.gt)
        data["tracker_ids"].append(fr.trk)
        data["similarity_scores"].append(np.maximum(0.0, 1.0 - d / 0.10))
    data["num_gt_dets"] = sum(len(g) for g in data["gt_ids"])
    data["num_tracker_dets"] = sum(len(t) for t in data["tracker_ids"])
    res = te.HOTA().eval_sequence(data)
    assert round(ours.hota, 4) == round(float(np.mean(res["HOTA"])), 4)
    assert round(ours.deta, 4) == round(float(np.mean(res["DetA"])), 4)
    assert round(ours.assa, 4) == round(float(np.mean(res["AssA"])), 4)


@pytest.mark.parametrize("case", ["no truth rows", "no tracks either", "truth outside the tracks' span"])
def test_no_ground_truth_measures_nothing(case):
    # MOTA was 1 - 0/0 -> 1.0, IDF1 1.0 and HOTA 0.0 on empty truth: claims about nothing
    tr = np.zeros(3, TRACK_DTYPE)
    tr["t_us"], tr["track_id"], tr["x_m"], tr["y_m"], tr["state"] = [0, 10_000, 20_000], "1", 0.5, 0.5, "confirmed"
    gt = np.zeros(2, TRUTH_DTYPE)
    gt["t_us"], gt["robot"], gt["x_m"], gt["y_m"] = [5_000_000, 5_010_000], "a", [0.5, 0.6], 0.5
    if case != "truth outside the tracks' span":
        gt = gt[:0]
    if case == "no tracks either":
        tr = tr[:0]
    s = evaluate(tr, gt)
    assert s.n_gt == 0
    for name in ("mota", "idf1", "idp", "hota", "deta", "assa", "recall", "mae_cm", "heading_mae_deg"):
        assert math.isnan(getattr(s, name)), name
    d = s.to_dict()
    assert (d["mota"], d["idf1"], d["hota"], d["mae_cm"]) == (None, None, None, None)


def test_a_negative_host_ns_is_a_format_error_naming_its_line(tmp_path):
    """An empty host_ns is absent (the row is left out on the host clock); a negative one is a
    broken value and names its line, not silently taken for absent (issue 20)."""
    from arena.formats.tables import CsvFormatError, read_tracks_csv

    p = tmp_path / "t.csv"
    p.write_text("t_us,track_id,x_m,y_m,host_ns\n"
                 "0,1,0.5,0.5,1000000\n"
                 "10000,1,0.5,0.5,\n"
                 "20000,1,0.5,0.5,-5\n"
                 "30000,1,0.5,0.5,31000000\n")
    with pytest.raises(CsvFormatError, match=r"line 4, column host_ns: -5 is negative"):
        read_tracks_csv(p, clock="host")
    p.write_text(p.read_text().replace("-5\n", "21000000\n"))
    tracks = read_tracks_csv(p, clock="host")   # the empty cell alone is left out
    assert tracks["t_us"].tolist() == [1000, 21000, 31000]
