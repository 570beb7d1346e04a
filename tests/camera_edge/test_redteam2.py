"""A red team's second round on the edge: `--list-devices` on a damaged or unreadable sysfs tree,
a looped file replaced between passes, and files of many skipped parts (counted once, logged
once, bounded memory, summed in the summary and the status)."""

from __future__ import annotations

import logging
import struct
import threading
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest

from arena.events import EVENT_DTYPE, make_events
from arena.formats import SkippedData
from arena.formats.aedat4 import Aedat4Writer

UNDESCRIBED = "packets of undescribed streams"


def _main(*args: str) -> int:
    from arena.cli import main

    try:
        return main(list(args))
    except SystemExit as exc:   # argparse's usage errors
        return exc.code


def _undescribed_then_events(path: Path, n_packets: int, n_events: int = 10) -> None:
    """An AEDAT4 file: ``n_packets`` empty packets of stream 9 (which its header does not
    describe), then one packet of ``n_events`` events (none when 0)."""
    w = Aedat4Writer(path, 320, 240, compression="none")
    w.close()
    with open(path, "ab") as f:
        f.write(struct.pack("<ii", 9, 0) * n_packets)
    if n_events:
        tmp = path.with_name("_events.aedat4")
        w = Aedat4Writer(tmp, 320, 240, compression="none")
        ev = np.zeros(n_events, EVENT_DTYPE)
        ev["t"] = np.arange(n_events)
        w.write(ev)
        w.close()
        data = tmp.read_bytes()
        header_size = struct.unpack_from("<I", data, 14)[0]
        with open(path, "ab") as f:
            f.write(data[18 + header_size:])
        tmp.unlink()


# -- 1. arena edge --list-devices ------------------------------------------------------------------

def test_list_devices_when_sysfs_cannot_be_searched_is_one_line_exit_2(monkeypatch, capsys):
    # /sys/bus/usb without search permission: Path.is_dir() raises EACCES (it only hides ENOENT)
    import sys

    from camera_edge.devices import SYSFS_USB

    monkeypatch.setitem(sys.modules, "usb.core", None)   # no pyusb: sysfs is the way
    real_is_dir = Path.is_dir

    def is_dir(self):
        if self == SYSFS_USB:
            raise PermissionError(13, "Permission denied", str(self))
        return real_is_dir(self)

    monkeypatch.setattr(Path, "is_dir", is_dir)
    code = _main("edge", "--list-devices")
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and "cannot list USB devices" in err and "Permission denied" in err, err


def test_sysfs_entries_that_cannot_be_read_or_are_not_hex_ids_are_named(tmp_path, monkeypatch):
    import os

    from camera_edge import devices

    def device(name, **files):
        d = tmp_path / name
        d.mkdir()
        for k, v in files.items():
            (d / k).write_text(v)

    device("1-1", idVendor="31f7", idProduct="0003", busnum="1", devnum="4", product="EVK4",
           serial="a\nb\x1b[31mRED")
    device("1-2", idVendor="31f7", idProduct="-0003")        # int(.., 16) took it: 31f7:-003
    device("1-3", idVendor="0x31f7", idProduct="0003")
    device("1-4", idVendor="31f7_0", idProduct="0003")
    device("1-5", idVendor="31f7", idProduct="0003")          # unreadable (below)
    device("1-6", idProduct="0003")
    (tmp_path / "1-6" / "idVendor").mkdir()                    # a folder, not a file
    device("1-7", idVendor="31f7", idProduct="0003")
    os.mkfifo(tmp_path / "1-7" / "product")                   # read_text() waited for a writer forever
    device("1-1:1.0", bInterfaceClass="ff")                    # an interface: no ids, not a note
    real_open = os.open

    def deny(path, *args, **kw):
        if Path(path) == tmp_path / "1-5" / "idVendor":
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, *args, **kw)

    monkeypatch.setattr(devices.os, "open", deny)
    notes: list[str] = []
    out: list = []
    t = threading.Thread(target=lambda: out.append(devices.sysfs_devices(tmp_path, notes)), daemon=True)
    t.start()
    t.join(10)
    assert out, "sysfs_devices hung on a FIFO"
    found = out[0]
    assert [(d.vendor_id, d.product_id, d.product, d.url) for d in found] == [
        (0x31F7, 3, "EVK4", "prophesee:a\nb\x1b[31mRED"), (0x31F7, 3, "", "prophesee:")]
    assert notes == [
        "USB entry 1-2 skipped: idProduct '-0003' is not a 4-digit hex USB id",
        "USB entry 1-3 skipped: idVendor '0x31f7' is not a 4-digit hex USB id",
        "USB entry 1-4 skipped: idVendor '31f7_0' is not a 4-digit hex USB id",
        "USB entry 1-5 skipped: idVendor cannot be read (Permission denied)",
        "USB entry 1-6 skipped: idVendor is not a file",
    ]   # 1-7 is listed, without the product name its FIFO does not give
    line = found[0].describe()
    assert "-> prophesee:a\\nb\\x1b[31mRED " in line and "\x1b" not in line and "\n" not in line, line


# -- 2. arena edge FILE --loop, the file replaced between passes ----------------------------------

def _two_packets(path: Path, width: int = 320, height: int = 240) -> np.ndarray:
    n = 2000
    ev = make_events(np.arange(n) % width, np.arange(n) % height, np.ones(n), np.arange(n) * 100)
    w = Aedat4Writer(path, width, height, compression="none", packet_events=1000)
    w.write(ev)
    w.close()
    return ev


@pytest.mark.parametrize("replacement,why", [
    (b"garbage", "bad magic"),
    (None, "no such file"),
    ("other size", "the sensor is now 640 x 480 px, not 320 x 240"),
])
def test_a_looped_file_replaced_between_passes_stops_the_replay_in_one_line(tmp_path, caplog, replacement, why):
    from camera_edge.sources import FileSource

    path = tmp_path / "loop.aedat4"
    ev = _two_packets(path)
    with FileSource(path, speed=0, loop=True) as src:
        first = np.concatenate([src.read(), src.read()])
        assert first.size == ev.size
        if replacement is None:
            path.unlink()
        elif replacement == "other size":
            _two_packets(path, 640, 480)
        else:
            path.write_bytes(replacement)
        with caplog.at_level(logging.WARNING, logger="camera_edge.sources"):
            assert src.read() is None      # it raised FormatError / FileNotFoundError
    assert why in caplog.text and "stopping the replay" in caplog.text, caplog.text


def test_a_truncated_file_is_logged_with_its_path_once(tmp_path, caplog):
    from camera_edge.sources import FileSource

    path = tmp_path / "trunc.aedat4"
    _two_packets(path)
    path.write_bytes(path.read_bytes()[:-50])
    with caplog.at_level(logging.WARNING, logger="camera_edge.sources"):
        with FileSource(path, speed=0) as src:
            got = [c for c in src]
    assert sum(c.size for c in got) == 1000
    [msg] = [r.getMessage() for r in caplog.records if "stopping the replay" in r.getMessage()]
    assert msg.count(str(path)) == 1 and "truncated" in msg, msg


# -- 3. the 'no events' pre-check: counted, not kept ----------------------------------------------

def test_no_events_precheck_counts_skips_in_bounded_memory_and_sums_them(tmp_path):
    from camera_edge.cli import _no_events

    path = tmp_path / "undescribed.aedat4"
    _undescribed_then_events(path, 20_000, n_events=0)
    tracemalloc.start()
    try:
        why = _no_events(str(path))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # one summed line (it was "1 packets ... skipped" three times); every warning was kept: ~10 MB
    assert why == f"no events in {path} (20000 {UNDESCRIBED} skipped)"
    assert peak < 2 << 20, peak
    _undescribed_then_events(path, 3)      # 3 skipped, then events: it has events
    assert _no_events(str(path)) is None


# -- 4. arena edge: each kind of skip logged once, counted in the summary and the status ----------

def test_file_source_logs_each_kind_of_skip_once_and_counts_them(tmp_path, caplog):
    from camera_edge.sources import FileSource

    path = tmp_path / "many.aedat4"
    _undescribed_then_events(path, 5000)
    with warnings.catch_warnings(record=True) as escaped, caplog.at_level(logging.WARNING, "camera_edge.sources"):
        warnings.simplefilter("always")
        with FileSource(path, speed=0, loop=True) as src:
            got = [src.read() for _ in range(3)]   # three passes
    assert sum(g.size for g in got) == 30
    assert src.skipped == {UNDESCRIBED: 15_000}
    assert [w for w in escaped if issubclass(w.category, SkippedData)] == []   # none printed raw
    logged = [r.getMessage() for r in caplog.records if "does not describe" in r.getMessage()]
    assert len(logged) == 1 and logged[0].count(str(path)) == 1, logged


def test_edge_puts_the_skips_in_its_summary_and_status(tmp_path, capsys):
    from arena.messages import Status, decode
    from arena.session import ZenohSettings, open_session
    from camera_edge.pipeline import EdgePipeline
    from camera_edge.service import run_edge
    from camera_edge.sources import FileSource

    path = tmp_path / "many.aedat4"
    _undescribed_then_events(path, 4000)
    status = []
    with open_session(ZenohSettings(mode="peer", connect=[], listen=[])) as s:
        s.declare_subscriber("arena/status/edge/camskip", lambda smp: status.append(decode(bytes(smp.payload))))
        res = run_edge(s, FileSource(path, speed=0), EdgePipeline(slice_us=10_000), "camskip", "planes-zstd/1")
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not status:
            time.sleep(0.02)
    assert res["skipped"] == {UNDESCRIBED: 4000} and res["invalid"] == 0
    final = [st for st in status if isinstance(st, Status)][-1]
    assert final.gauges["source_skipped"] == 4000 and final.gauges["source_invalid"] == 0


def test_edge_summary_line_says_what_was_skipped_like_convert(tmp_path, capsys):
    path = tmp_path / "many.aedat4"
    _undescribed_then_events(path, 3000)
    code = _main("edge", str(path), "--camera", "camsum", "--speed", "0", "-m", "peer", "-l", "tcp/127.0.0.1:0")
    err = capsys.readouterr().err
    assert code == 0, err
    assert err.count("\n") <= 3, err   # the first skip logged, the summary: not 6000 lines
    assert "arena edge camsum: 10 events in, 10 kept" in err and f", 3000 {UNDESCRIBED} skipped\n" in err, err


def test_a_write_that_fails_part_way_names_the_files_it_was_converting(tmp_path):
    # a file-size limit (EFBIG): the OSError of a write names no file; the one line says which
    import resource
    import subprocess
    import sys

    from arena.formats import write_events
    n = 20_000
    src, dst = tmp_path / "in.npy", tmp_path / "out.raw"
    write_events(src, make_events(np.arange(n) % 320, np.arange(n) % 240, np.arange(n) % 2, np.arange(n) * 10),
                 320, 240)

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (8192, 8192))   # Python ignores SIGXFSZ: EFBIG

    res = subprocess.run([sys.executable, "-m", "arena", "convert", str(src), str(dst)], capture_output=True,
                         text=True, timeout=120, preexec_fn=small_files)
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip() == f"arena convert: converting {src} to {dst}: File too large", res.stderr
