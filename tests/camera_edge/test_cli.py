"""`arena convert` and `arena edge` command lines: real subprocesses, clear errors, no tracebacks."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

from arena.events import make_events
from arena.formats import read_events, write_events
from tests.conftest import arena_cmd


def _run(*args, timeout=60):
    return subprocess.run(arena_cmd(*args), capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def events():
    rng = np.random.default_rng(0)
    n = 5000
    return make_events(rng.integers(0, 640, n), rng.integers(0, 480, n), rng.integers(0, 2, n),
                       (1 << 25) + np.sort(rng.integers(0, 2_000_000, n)))


@pytest.mark.slow
def test_convert_chain_keeps_every_event_and_absolute_time(tmp_path, events):
    write_events(tmp_path / "a.npz", events, 640, 480)
    chain = ["a.npz", "b.raw", "c.aedat4", "d.dat", "e.csv", "f.raw", "g.npz"]
    for src, dst in zip(chain, chain[1:]):
        extra = ["--evt", "2"] if dst == "f.raw" else []
        r = _run("convert", str(tmp_path / src), str(tmp_path / dst), *extra)
        assert r.returncode == 0, r.stderr
        assert f"{events.size} events, 640 x 480 px" in r.stdout
    out, w, h = read_events(tmp_path / "g.npz")
    np.testing.assert_array_equal(out, events)
    assert (w, h) == (640, 480)


@pytest.mark.parametrize("make,args,message", [
    (None, ["missing.raw", "x.npz"], "no such file"),
    (b"1,2,3,4\n", ["in.csv", "out.xyz"], "unknown extension"),
    (b"% evt 3.0\n\x01", ["in.raw", "in.raw"], "same file"),
    (b"1,2,1,4\n3,4,x,5\n", ["in.csv", "out.npz"], "non-numeric"),
])
def test_convert_errors_are_one_clear_line(tmp_path, make, args, message):
    if make is not None:
        (tmp_path / args[0]).write_bytes(make)
    r = _run("convert", *[str(tmp_path / a) for a in args])
    assert r.returncode == 2
    assert message in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / args[1]).exists() or args[0] == args[1]


def test_convert_csv_takes_the_sensor_size(tmp_path):
    (tmp_path / "p.csv").write_text("x,y,p,t_us\n1,2,1,100\n3,4,0,200\n")
    r = _run("convert", str(tmp_path / "p.csv"), str(tmp_path / "p.raw"), "--size", "1280x720")
    assert r.returncode == 0, r.stderr
    ev, w, h = read_events(tmp_path / "p.raw")
    assert (w, h) == (1280, 720) and ev["t"].tolist() == [100, 200]


@pytest.mark.parametrize("args,message", [
    (["nowhere.raw", "--camera", "c"], "no such file"),
    (["udp://x", "--camera", "c"], "unknown event source"),
    (["x.raw", "--camera", "bad/name"], "camera name"),
    (["tcp://127.0.0.1:1", "--camera", "c", "--loop"], "--loop applies to file"),
    ([], "give a SOURCE"),
    (["x.raw", "--camera", "c", "--hot-save", "h.txt"], "needs --hot-pixels learn"),
])
def test_edge_errors_are_one_clear_line(args, message):
    r = _run("edge", *args)
    assert r.returncode == 2, r.stderr
    assert message in r.stderr and "Traceback" not in r.stderr


def test_edge_list_devices_and_help():
    r = _run("edge", "--list-devices")
    assert r.returncode == 0 and ("no event camera found" in r.stdout or "->" in r.stdout)
    r = _run("edge", "--help")
    assert "Examples:" in r.stdout and "--denoise" in r.stdout
    r = _run("convert", "--help")
    assert "Examples:" in r.stdout


def test_lab_options_fill_unset_flags_and_are_checked():
    import argparse

    from camera_edge.cli import LAB_OPTIONS, _apply_lab_options

    args = argparse.Namespace(**{k: None for k in LAB_OPTIONS})
    args.codec = "raw/1"  # a flag wins over the lab config
    assert _apply_lab_options(args, {"slice_ms": 20, "codec": "planes-zstd/1", "denoise": 5000}) is None
    assert (args.slice_ms, args.codec, args.denoise, args.queue) == (20.0, "raw/1", 5000, 32)
    args = argparse.Namespace(**{k: None for k in LAB_OPTIONS})
    assert "services.edge: unknown key(s) slice; known: slice_ms" in _apply_lab_options(args, {"slice": 3})
    args = argparse.Namespace(**{k: None for k in LAB_OPTIONS})
    assert "services.edge.queue: expected an integer >= 1, got 'big'" in _apply_lab_options(args, {"queue": "big"})
    args = argparse.Namespace(**{k: None for k in LAB_OPTIONS})
    assert _apply_lab_options(args, {"denoise": True}) is None and args.denoise == 10_000
    args = argparse.Namespace(**{k: None for k in LAB_OPTIONS})
    assert "services.edge.denoise: expected an integer > 0 or true" in _apply_lab_options(args, {"denoise": "x"})


def test_edge_lab_option_mistakes_are_one_clear_line_naming_file_table_and_key(tmp_path):
    lab = tmp_path / "lab.toml"
    lab.write_text('[[cameras]]\nname = "camx"\nsource = "nowhere.aedat4"\n[services.edge]\nslice_ms = "fast"\n')
    r = _run("edge", "--lab", str(lab))
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert f"arena edge: {lab}: services.edge.slice_ms: expected a finite number > 0, got 'fast'" in r.stderr


def test_edge_reads_its_camera_from_the_lab_config(tmp_path):
    (tmp_path / "lab.toml").write_text('[[cameras]]\nname = "camx"\nsource = "nowhere.aedat4"\n'
                                       '[services.edge]\nslice_ms = 5\n')
    r = _run("edge", "--lab", str(tmp_path / "lab.toml"))
    assert r.returncode == 2 and "nowhere.aedat4" in r.stderr and "Traceback" not in r.stderr
