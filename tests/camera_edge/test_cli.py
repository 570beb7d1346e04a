"""`arena convert` and `arena edge` command lines: real subprocesses, clear errors, no tracebacks."""

from __future__ import annotations

import subprocess
from pathlib import Path

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
    # a machine with libusb or sysfs lists (or finds no camera); one with neither (a container)
    # says what to install, in one line
    if r.returncode == 0:
        assert "no event camera found" in r.stdout or "->" in r.stdout
    else:
        assert r.returncode == 2 and "install libusb-1.0" in r.stderr and "Traceback" not in r.stderr
        assert not Path("/sys/bus/usb/devices").is_dir()
    r = _run("edge", "--help")
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


# An outsider's report: empty inputs and absurd numbers were accepted. In-process (arena.cli.main),
# parse errors and tiny files only.
def _main(*args: str) -> int:
    from arena.cli import main

    try:
        return main(list(args))
    except SystemExit as exc:   # argparse's usage errors
        return exc.code


def _empty_files(tmp_path) -> list:
    """A 0-byte file of each readable format, and one with a valid header but no event."""
    from arena.events import empty_events

    files = []
    for ext in ("raw", "dat", "aedat4", "csv", "npy", "npz"):
        (tmp_path / f"zero.{ext}").write_bytes(b"")
        write_events(tmp_path / f"header.{ext}", empty_events(0), 640, 480)
        files += [tmp_path / f"zero.{ext}", tmp_path / f"header.{ext}"]
    return files


def test_convert_of_a_raw_file_of_unknown_words_says_what_was_skipped(tmp_path, capsys):
    """A RAW body of 0xFF words only (a red team's file) said "a header without events"."""
    raw = tmp_path / "ff.raw"
    raw.write_bytes(b"% evt 3.0\n% format EVT3;height=480;width=640\n% end\n" + b"\xff" * 100_000)
    assert _main("convert", str(raw), str(tmp_path / "ff.csv")) == 2
    err = capsys.readouterr().err
    assert "no events in" in err and "(50000 words of no known type skipped)" in err, err


def test_convert_of_a_file_without_events_says_so_and_writes_nothing(tmp_path, capsys):
    for src in _empty_files(tmp_path):
        out = tmp_path / f"out-{src.name}.npz"
        code = _main("convert", str(src), str(out))
        err = capsys.readouterr().err
        assert code == 2, (src.name, err)
        assert f"no events in {src}" in err and "nothing written" in err and "Traceback" not in err, err
        assert not out.exists(), src.name
    (tmp_path / "bad.csv").write_text("1,2,3,4\n")   # polarity 3: its only event is invalid
    assert _main("convert", str(tmp_path / "bad.csv"), str(tmp_path / "bad.npz")) == 2
    assert "(1 invalid events skipped)" in capsys.readouterr().err and not (tmp_path / "bad.npz").exists()
    (tmp_path / "one.csv").write_text("1,2,1,4\n")   # one event: converted as before
    assert _main("convert", str(tmp_path / "one.csv"), str(tmp_path / "one.npz")) == 0
    assert read_events(tmp_path / "one.npz")[0].size == 1


def test_edge_on_a_file_without_events_says_so_before_waiting_for_zenoh(tmp_path, capsys):
    for src in _empty_files(tmp_path):
        code = _main("edge", str(src), "--camera", "c", "--duration", "1")
        err = capsys.readouterr().err
        assert code == 2, (src.name, err)
        assert f"arena edge: no events in {src}" in err and "Traceback" not in err, err


@pytest.mark.parametrize("args,expected", [
    (["--slice-ms=nan"], "[0.001, 1000] ms"),
    (["--slice-ms=1e9"], "[0.001, 1000] ms"),
    (["--slice-ms=0"], "[0.001, 1000] ms"),
    (["--speed=inf"], "[0, 1000] x real time"),
    (["--speed=nan"], "[0, 1000] x real time"),
    (["--speed=-1"], "[0, 1000] x real time"),
    (["--hot-learn-s=nan"], "(0, 600] s"),
    (["--hot-learn-s=-1"], "(0, 600] s"),
    (["--roi-margin=-3"], "[0, 4096] px"),
    (["--denoise=0"], "[1, 1000000] µs"),
    (["--denoise=-5"], "[1, 1000000] µs"),
    (["--queue=0"], "[1, 10000] windows"),
    (["--queue=1e9"], "[1, 10000] windows"),
    (["--duration=nan"], "seconds in (0, 604800]"),
    (["--duration=-1"], "seconds in (0, 604800]"),
])
def test_edge_absurd_numbers_are_usage_errors_naming_range_and_unit(args, expected, capsys):
    code = _main("edge", "x.raw", "--camera", "c", *args)
    err = capsys.readouterr().err
    assert code == 2 and expected in err and args[0].split("=")[0] in err, err


def test_edge_lab_values_get_the_same_ranges():
    import argparse

    from camera_edge.cli import LAB_OPTIONS, _apply_lab_options

    args = argparse.Namespace(**{k: None for k in LAB_OPTIONS})
    assert "--slice-ms (slice_ms) must be a number in [0.001, 1000] ms" in _apply_lab_options(args, {"slice_ms": 1e9})
    args = argparse.Namespace(**{k: None for k in LAB_OPTIONS})
    assert "--queue (queue) must be an integer in [1, 10000]" in _apply_lab_options(args, {"queue": 10**9})


@pytest.mark.parametrize("size", ["70000x480", "640x0", "nanxnan"])
def test_convert_size_beyond_any_sensor_is_a_usage_error(size, capsys, tmp_path):
    (tmp_path / "one.csv").write_text("1,2,1,4\n")
    code = _main("convert", str(tmp_path / "one.csv"), str(tmp_path / "one.npz"), "--size", size)
    err = capsys.readouterr().err
    assert code == 2 and "each 1-65535" in err, err
    assert not (tmp_path / "one.npz").exists()


def test_cameras_are_listed_from_sysfs_without_libusb(tmp_path):
    # a fresh machine often has pyusb but no libusb: the Linux sysfs tree lists the cameras
    from camera_edge.devices import sysfs_devices

    def device(name, **files):
        d = tmp_path / name
        d.mkdir()
        for k, v in files.items():
            (d / k).write_text(v + "\n")

    device("1-1", idVendor="31f7", idProduct="0003", busnum="1", devnum="4", product="EVK4", serial="00ca0009")
    device("1-2", idVendor="046d", idProduct="0825", busnum="1", devnum="5", product="Webcam C270")
    device("2-1", idVendor="152a", idProduct="8419", busnum="2", devnum="2", product="DVXplorer")
    device("1-1:1.0", bInterfaceClass="ff")                 # an interface folder: no ids
    device("usb1", idVendor="zz", idProduct="0002")         # unreadable ids
    found = sysfs_devices(tmp_path)
    assert [(d.vendor, d.vendor_id, d.product_id, d.bus, d.address, d.product, d.url) for d in found] == [
        ("Prophesee", 0x31F7, 0x0003, 1, 4, "EVK4", "prophesee:00ca0009"),
        ("iniVation", 0x152A, 0x8419, 2, 2, "DVXplorer", "inivation:"),
    ]
    assert "-> prophesee:00ca0009" in found[0].describe()
    with pytest.raises(RuntimeError, match="cannot be read"):   # the CLI prints it, exit 2
        sysfs_devices(tmp_path / "1-1" / "idVendor")
