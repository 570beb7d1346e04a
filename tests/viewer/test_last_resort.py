"""The viewer's last-resort handler: a sample its state cannot take is counted in ``bad``, logged
with the exception, and the next samples are shown."""

from __future__ import annotations

import logging
import time

from arena.messages import Track
from arena.session import open_session
from viewer.service import handle_sample, subscribe
from viewer.state import ViewerState


class RefusingState(ViewerState):
    """A ViewerState whose track update fails for robot "broken". Fuzzing every message type
    with extreme valid values (3000 x 30 samples) found no sample that makes the real state
    raise, so the failure is injected here, through the public constructor argument."""

    def on_track(self, key, msg):
        if msg.robot == "broken":
            raise MemoryError("cannot allocate the trail")
        super().on_track(key, msg)


def _track(robot: str, x: float) -> bytes:
    return Track(track_id=1, robot=robot, camera="c0", stamp_us=1, x=x, y=0.5, yaw=0.0).encode()


def test_a_sample_the_state_cannot_take_is_counted_logged_and_the_next_one_shown(caplog):
    state = RefusingState()
    with caplog.at_level(logging.WARNING, logger="arena.viewer"):
        handle_sample(state, "arena/robots/broken", _track("broken", 0.1))   # does not raise
        handle_sample(state, "arena/robots/zumo1", _track("zumo1", 0.7))
    assert state.counts["bad"] == 1 and state.counts["tracks"] == 1
    assert [t["x"] for t in state.snapshot()["tracks"]] == [0.7]
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and "MemoryError: cannot allocate the trail" in said[0] and "(1 so far)" in said[0]


def test_the_viewer_subscriber_goes_on_after_a_failing_sample(router):
    state = RefusingState()
    with open_session(router.settings("client")) as viewer, open_session(router.settings("client")) as s:
        subs = subscribe(viewer, state)
        try:
            pub_bad = s.declare_publisher("arena/robots/broken")
            pub_good = s.declare_publisher("arena/robots/zumo1")
            deadline = time.monotonic() + 20
            x = 0.0
            while time.monotonic() < deadline and not (state.counts["bad"] >= 1 and state.counts["tracks"] >= 1):
                pub_bad.put(_track("broken", 0.1))   # repeated until the subscription is up
                x += 0.01
                pub_good.put(_track("zumo1", x))
                time.sleep(0.05)
            n_bad = state.counts["bad"]
            pub_bad.put(_track("broken", 0.1))
            pub_good.put(_track("zumo1", 1.5))
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline and state.counts["bad"] == n_bad:
                time.sleep(0.02)
            while time.monotonic() < deadline and [t["x"] for t in state.snapshot()["tracks"]] != [1.5]:
                time.sleep(0.02)
        finally:
            for sub in subs:
                sub.undeclare()
    assert state.counts["bad"] == n_bad + 1
    assert [t["x"] for t in state.snapshot()["tracks"]] == [1.5]
