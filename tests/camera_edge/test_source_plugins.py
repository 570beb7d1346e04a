"""Event sources as plug-ins (python-can style): a package registers a scheme in the entry-point
group ``arena.sources`` and ``open_source``/``arena edge`` use it. The plug-in here is real
installed metadata: a ``*.dist-info`` folder (METADATA + entry_points.txt) and its module in a
temporary folder on PYTHONPATH of a subprocess, as pip would leave them."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from arena.codec import decode as decode_events
from arena.messages import EventWindow
from arena.session import open_session
from tests.conftest import REPO, arena_cmd

PLUGIN = '''
import numpy as np
from arena.events import make_events
from camera_edge.sources import EventSource


def fake_events(n):
    k = np.arange(n)
    return make_events(k % 64, (3 * k) % 48, k % 2, 10_000 + 997 * k)


class FakeSource(EventSource):
    """fake:N -- N events at 10 000 + 997 k us, in chunks of 7, then the end of the stream."""

    def __init__(self, url, **opts):
        super().__init__()
        self.width, self.height, self.name = 64, 48, f"fake {url}"
        ev = fake_events(int(url.split(":", 1)[1] or 5))
        self._chunks = [ev[i:i + 7] for i in range(0, ev.size, 7)]
        self.opts = opts

    def read(self, timeout=0.1):
        if not self._chunks:
            return None
        ev = self._chunks.pop(0)
        self._note_time(ev)
        return ev

    def close(self):
        self._chunks = []


class NoClose(EventSource):   # forgot close(): an EventSource must release its device
    def __init__(self, url):
        super().__init__()

    def read(self, timeout=0.1):
        return None


def busy(url):
    raise OSError("device busy")


def not_a_source(url):
    return [1, 2, 3]
'''

ENTRY_POINTS = """\
[arena.sources]
fake = arena_fakecam:FakeSource
noclose = arena_fakecam:NoClose
busy = arena_fakecam:busy
wrong = arena_fakecam:not_a_source
gone = arena_fakecam_gone:Source
tcp = arena_fakecam:FakeSource
"""


@pytest.fixture
def plugin_env(tmp_path) -> dict:
    """Environment whose PYTHONPATH holds an installed plug-in distribution ``arena-fakecam``."""
    site = tmp_path / "site"
    dist = site / "arena_fakecam-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: arena-fakecam\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(ENTRY_POINTS)
    (site / "arena_fakecam.py").write_text(PLUGIN)
    path = os.pathsep.join(p for p in (str(site), str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PYTHONPATH": path, "PYTHONUNBUFFERED": "1"}


OPEN_ALL = r"""
import json
import numpy as np
from camera_edge.sources import SourceError, TcpSource, open_source, source_plugins

out = {"plugins": sorted(source_plugins())}
with open_source("fake:23", speed=0, color="red") as src:
    parts = []
    while (ev := src.read()) is not None:
        parts.append(ev)
    ev = np.concatenate(parts)
    out["fake"] = {"type": type(src).__name__, "name": src.name, "size": [src.width, src.height],
                   "t": ev["t"].tolist(), "x": ev["x"].tolist(), "time_us": src.time_us, "opts": src.opts}
    src.close()
    out["after_close"] = src.read() is None
errors = {}
for url in ("noclose:", "busy:", "wrong:", "gone:", "udp://x"):
    try:
        open_source(url)
    except SourceError as exc:
        errors[url] = str(exc)
out["errors"] = errors
try:   # a built-in scheme is not taken over by a plug-in of the same name
    open_source("tcp://host-without-port")
except SourceError as exc:
    out["tcp"] = str(exc)
print(json.dumps(out))
"""


def test_a_plugin_scheme_opens_its_source_and_bad_plugins_are_clear_errors(plugin_env):
    r = subprocess.run([sys.executable, "-c", OPEN_ALL], env=plugin_env, capture_output=True, text=True,
                       timeout=60, cwd=REPO)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["plugins"] == ["busy", "fake", "gone", "noclose", "wrong"]   # tcp stays built in
    fake = out["fake"]
    k = np.arange(23)
    assert fake["type"] == "FakeSource" and fake["name"] == "fake fake:23" and fake["size"] == [64, 48]
    assert fake["t"] == (10_000 + 997 * k).tolist() and fake["x"] == (k % 64).tolist()
    assert fake["time_us"] == 10_000 + 997 * 22
    assert fake["opts"] == {"color": "red"}         # options go to the plug-in, speed only to files
    assert out["after_close"]
    err = out["errors"]
    assert "plug-in 'noclose'" in err["noclose:"] and "abstract" in err["noclose:"] and "close" in err["noclose:"]
    assert "from arena-fakecam 0.1" in err["noclose:"]
    assert "cannot open 'busy:'" in err["busy:"] and "OSError: device busy" in err["busy:"]
    assert "returned a list, not a camera_edge.sources.EventSource" in err["wrong:"]
    assert "cannot be loaded" in err["gone:"] and "arena_fakecam_gone" in err["gone:"] and "reinstall" in err["gone:"]
    unknown = err["udp://x"]
    assert unknown.startswith("unknown event source 'udp://x'") and "tcp://HOST:PORT" in unknown and ".aedat4" in unknown
    assert "installed: busy:, fake:, gone:, noclose:, wrong:" in unknown
    assert "HOST:PORT" in out["tcp"]


def test_unknown_scheme_without_plugins_says_how_to_add_one():
    from camera_edge.sources import SourceError, open_source

    with pytest.raises(SourceError, match="unknown event source 'nosuch:1'.*none installed.*'arena.sources'"):
        open_source("nosuch:1")


def _wait(cond, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError(f"{what} within {timeout} s")


@pytest.mark.slow
def test_arena_edge_publishes_a_plugin_sources_events(router, plugin_env):
    got: dict[int, EventWindow] = {}
    lock = threading.Lock()

    def on_window(sample) -> None:
        msg = EventWindow.decode(bytes(sample.payload))
        with lock:
            got[msg.seq] = msg

    key = "arena/events/fk"
    with open_session(router.settings("client")) as s, open_session(router.settings("client")) as probe:
        s.declare_subscriber(key, on_window)
        pub = probe.declare_publisher(key)   # the router knows the subscriber before the edge connects
        _wait(lambda: pub.matching_status.matching, 10, "the router never matched the subscriber")
        pub.undeclare()
        r = subprocess.run(arena_cmd("edge", "fake:40", "--camera", "fk", *router.args), env=plugin_env,
                           capture_output=True, text=True, timeout=120, cwd=REPO)
        assert r.returncode == 0, r.stderr
        assert "fk: 40 events in, 40 kept" in r.stderr, r.stderr
        n = int(r.stderr.split(" windows,")[0].rsplit(" ", 1)[1])
        _wait(lambda: len(got) >= n, 10, f"the subscriber did not get all {n} windows")
    with lock:
        msgs = [got[k] for k in sorted(got)]
    assert [(m.width, m.height) for m in msgs] == [(64, 48)] * n
    assert [m.t_end_us for m in msgs] == [20_000, 30_000, 40_000, 50_000]   # last event: 48 883 µs
    ev = np.concatenate([decode_events(m.codec, bytes(m.data), m.count) for m in msgs])
    k = np.arange(40)
    np.testing.assert_array_equal(ev["t"], 10_000 + 997 * k)
    np.testing.assert_array_equal(ev["x"], k % 64)
    np.testing.assert_array_equal(ev["y"], (3 * k) % 48)


def test_inivation_source_close_ends_reading(tmp_path):
    dv = pytest.importorskip("dv_processing", reason="dv-processing (the 'inivation' extra) is not installed")
    from arena.events import make_events
    from arena.formats import write_events
    from camera_edge.sources import EventSource, InivationSource

    k = np.arange(20_000)
    write_events(tmp_path / "r.aedat4", make_events(k % 640, k % 480, k % 2, 5 * k), 640, 480)
    with InivationSource("rec", reader=dv.io.MonoCameraRecording(str(tmp_path / "r.aedat4"))) as src:
        assert isinstance(src, EventSource)
        first = src.read(timeout=0.01)
        assert first is not None and first.size > 0
        src.close()
        assert src.read(timeout=0.01) is None
        src.close()   # idempotent


def test_event_source_is_abstract_with_read_and_close():
    from camera_edge.sources import EventSource

    assert EventSource.__abstractmethods__ == frozenset({"read", "close"})
    with pytest.raises(TypeError, match="close"):
        type("OnlyRead", (EventSource,), {"read": lambda self, timeout=0.1: None})()
