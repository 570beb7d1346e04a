"""The live tracker's state file is validated like a message: a file that is invalid in any way
is renamed ``<file>.bad``, one warning names the problem, and the tracker starts afresh (real
files, real `arena track` processes on a real router)."""

from __future__ import annotations

import json
import os
import subprocess
import time

import pytest

from tests.conftest import arena_cmd
from tests.tracker.synth import calibration_dict
from tracker.service import MAX_STATE_BYTES, check_state, load_state

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


def good_state(camera: str = "c0") -> dict:
    """A state as the tracker writes it: one robot, named, restored at rest."""
    return {"camera": camera, "written_s": time.time(), "fleet": {"v": 1, "next_id": 3, "tracks": [
        {"id": 2, "robot": "zumo1", "x": 0.5, "y": 0.6, "vx": 0.1, "vy": 0.0, "yaw": 0.3, "u": 145.0,
         "v": 310.0, "t_us": 1_000_000, "last_seen_us": 990_000, "hits": 40}]}}


def _track(s: dict) -> dict:
    return s["fleet"]["tracks"][0]


# (name, how to spoil a good state, what the error says)
SPOILED = [
    ("written_s null", lambda s: s.update(written_s=None), "written_s is missing or null"),
    ("written_s a string", lambda s: s.update(written_s="yesterday"), "written_s is a str"),
    ("written_s Infinity", lambda s: s.update(written_s=float("inf")), "written_s is inf"),
    ("id Infinity", lambda s: _track(s).update(id=float("inf")), "tracks[0].id is inf, expected an integer"),
    ("id NaN", lambda s: _track(s).update(id=float("nan")), "tracks[0].id is nan"),
    ("id negative", lambda s: _track(s).update(id=-4), "tracks[0].id = -4 is outside"),
    ("id 2**70", lambda s: _track(s).update(id=2 ** 70), f"tracks[0].id = {2 ** 70} is outside"),
    ("id a float", lambda s: _track(s).update(id=2.0), "tracks[0].id is 2.0, expected an integer"),
    ("id a bool", lambda s: _track(s).update(id=True), "tracks[0].id is bool"),
    ("x NaN", lambda s: _track(s).update(x=float("nan")), "tracks[0].x is nan"),
    ("y far away", lambda s: _track(s).update(y=1e9), "tracks[0].y = 1e+09 is outside"),
    ("yaw a list", lambda s: _track(s).update(yaw=[1]), "tracks[0].yaw is a list"),
    ("t_us null", lambda s: _track(s).update(t_us=None), "tracks[0].t_us is NoneType"),
    ("t_us 2**63", lambda s: _track(s).update(t_us=2 ** 63), "tracks[0].t_us"),
    ("robot not a name", lambda s: _track(s).update(robot="a/b"), "tracks[0].robot"),
    ("robot a number", lambda s: _track(s).update(robot=7), "tracks[0].robot is int"),
    ("track a list", lambda s: s["fleet"]["tracks"].__setitem__(0, [1, 2]), "tracks[0] is list"),
    ("tracks an object", lambda s: s["fleet"].update(tracks={"id": 1}), "fleet.tracks is dict"),
    ("too many tracks", lambda s: s["fleet"].update(tracks=[_track(s)] * 257), "257 tracks, at most 256"),
    ("fleet a list", lambda s: s.update(fleet=[]), "'fleet' is list"),
    ("next_id Infinity", lambda s: s["fleet"].update(next_id=float("inf")), "fleet.next_id is inf"),
    ("camera a number", lambda s: s.update(camera=3), "'camera' is int"),
]


@pytest.mark.parametrize("name,spoil,says", SPOILED, ids=[c[0] for c in SPOILED])
def test_check_state_names_the_problem(name, spoil, says):
    state = good_state()
    spoil(state)
    with pytest.raises(ValueError) as err:
        check_state(state)
    assert says in str(err.value)


def test_check_state_accepts_what_the_tracker_writes_and_ignores_unknown_keys():
    from tracker.calibration import Calibration
    from tracker.pipeline import Pipeline
    from tracker.service import LiveTracker

    s = good_state()
    assert check_state(s) is s and s == {**good_state(), "written_s": s["written_s"]}
    live = LiveTracker(Pipeline(Calibration.from_dict(calibration_dict())), "c0")
    assert check_state(live.snapshot())["fleet"]["tracks"] == []
    s = good_state()
    s["extra"] = {"anything": [1, 2]}
    _track(s)["later_field"] = "x"
    for k in ("vx", "vy", "yaw", "u", "v", "last_seen_us", "hits"):   # optional
        _track(s).pop(k)
    assert check_state(s) is s
    for bad in ([], "x", 3, None):
        with pytest.raises(ValueError, match="expected an object"):
            check_state(bad)


def test_load_state_reads_at_most_the_size_cap_and_refuses_deep_nesting(tmp_path):
    big = tmp_path / "big.json"
    with open(big, "wb") as fh:                      # 20 MB: never read whole
        fh.write(b'{"camera": "c0", "pad": "')
        fh.write(b"x" * (20 << 20))
        fh.write(b'"}')
    with pytest.raises(ValueError, match=f"larger than {MAX_STATE_BYTES} bytes"):
        load_state(big, "c0", 600)
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 500_000 + "]" * 500_000)   # within the cap, but nested beyond any parser
    with pytest.raises(ValueError, match="not JSON"):
        load_state(deep, "c0", 600)
    future = tmp_path / "future.json"
    future.write_text(json.dumps({**good_state(), "written_s": time.time() + 3600}))
    fleet, why = load_state(future, "c0", 600)      # a clock was wrong: not restored, not an error
    assert fleet is None and "in the future" in why


def _files(tmp_path) -> dict[str, bytes]:
    """Bad state files: name -> content."""
    def spoilt(f) -> bytes:
        s = good_state()
        f(s)
        return json.dumps(s).encode()          # Python's json writes NaN/Infinity as JS literals

    files = {
        "written_null": spoilt(lambda s: s.update(written_s=None)),
        "id_infinity": spoilt(lambda s: _track(s).update(id=float("inf"))),
        "id_negative": spoilt(lambda s: _track(s).update(id=-4)),
        "id_2_70": spoilt(lambda s: _track(s).update(id=2 ** 70)),
        "truncated": json.dumps(good_state()).encode()[:-20],
        "not_object": b"[1, 2, 3]",
        "nested_types": spoilt(lambda s: s["fleet"].update(tracks=[{"id": "one", "x": [], "y": {}}])),
        "huge": b'{"camera": "c0", "pad": "' + b"x" * (20 << 20) + b'"}',
    }
    assert b"Infinity" in files["id_infinity"]
    return files


@pytest.mark.slow
def test_a_bad_state_file_is_set_aside_and_the_tracker_starts_afresh(router, tmp_path):
    """Each bad file: `arena track` starts (runs its loop, exits 0), the file is renamed .bad
    (byte for byte), one warning names the problem, and the state it writes is a fresh fleet.
    Before the fix `written_s: null` and `id: Infinity` made every start fail (TypeError,
    OverflowError), and ids -4 / 2**70 were restored (2**70 then broke every publish)."""
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps(calibration_dict()))
    files = _files(tmp_path)
    expect = {"written_null": "written_s is missing or null", "id_infinity": "id is inf",
              "id_negative": "id = -4 is outside", "id_2_70": "is outside", "truncated": "not JSON",
              "not_object": "JSON list, expected an object", "nested_types": "tracks[0].id is str",
              "huge": "larger than"}
    procs = {}
    for name, content in files.items():
        path = tmp_path / f"{name}.json"
        path.write_bytes(content)
        if name == "truncated":   # an older .bad is replaced: one is kept
            path.with_name(path.name + ".bad").write_bytes(b"an older bad file")
        procs[name] = subprocess.Popen(
            arena_cmd("track", "--camera", "c0", "--calibration", str(calib), "--state", str(path),
                      "--name", f"t-{name.replace('_', '-')}", "--duration", "2", *router.args),
            env=ENV, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 240
    results = {}
    for name, p in procs.items():
        try:
            _, err = p.communicate(timeout=max(1.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            _, err = p.communicate(timeout=10)
        results[name] = (p.returncode, err)
    for name, content in files.items():
        rc, err = results[name]
        path = tmp_path / f"{name}.json"
        assert rc == 0, f"{name}: the tracker did not start and run: {err}"
        warnings = [ln for ln in err.splitlines() if "starting afresh" in ln]
        assert len(warnings) == 1 and expect[name] in warnings[0] and ".bad" in warnings[0], f"{name}: {err}"
        assert path.with_name(path.name + ".bad").read_bytes() == content, name
        fresh = json.loads(path.read_text())          # written at exit: the fresh fleet
        assert fresh["camera"] == "c0" and fresh["fleet"]["tracks"] == [] and fresh["fleet"]["next_id"] == 1, name
