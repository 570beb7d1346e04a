"""The live tracker: ``arena/events/<camera>`` in, ``arena/robots/<id>`` out.

- Event windows arrive in a bounded :class:`Inbox` (keeps the newest ``queue`` slices, so a
  lagging tracker drops the oldest, counted as ``windows_dropped_in_queue``, and never works on
  stale data; the worker sleeps until a window arrives instead of polling); one worker
  (the main thread) decodes them with :func:`arena.codec.decode` and feeds the
  :class:`tracker.pipeline.Pipeline` in time order. A slice that does not decode, does not
  fit the calibrated sensor or is not newer than the last one is counted and skipped.
- Every track update is published on ``arena/robots/<id>`` (the robot's name when known,
  else the track number) as an :class:`arena.messages.Track`; ``get("arena/robots/*")``
  answers with the current fleet; tracks can also be logged to CSV.
- Names (which track is which robot) come from two sources, both through the fleet tracker's
  ``set_robot_name``: the robots' own telemetry (``arena/telemetry/<robot>``: tread speeds and
  gyro matched to each track's motion over a few seconds, time-aligned on the robot's clock;
  :mod:`tracker.naming`), which every lab has, and ``arena/groundtruth/<robot>`` poses (e.g. the
  webcam's markers) that keep falling on the same track, each compared with the track's pose *at
  the pose's capture stamp* (interpolated in the track's recent history), not with the latest
  track: a webcam that lags on a loaded host still names the right track. Counted in
  ``names_from_telemetry`` and ``names_from_groundtruth`` (a name given or moved to another track);
  ``telemetry_bad``, ``groundtruth_bad`` (undecodable messages), ``groundtruth_out_of_history``
  (a pose stamped where no track has history: not used).
- Presence and once-a-second status through :class:`arena.service.Service`: counters
  ``windows_in``, ``windows_bad``, ``windows_late``, ``events_late`` (events older than their
  window's start: the edge keeps them in the window open when they came), ``windows_missed`` (sequence gaps not
  explained by the edge's own ``dropped`` count, which go to ``windows_dropped_at_edge``, nor by
  our own full queue, ``windows_dropped_in_queue``: windows lost on the way),
  ``tracks_out``, ``stream_restarts`` (the camera's clock jumped back by > 1 s: a replay
  looping; tracking starts afresh), ``windows_future`` and ``windows_past`` (windows held, not
  processed, because they jumped more than 1 s ahead of the stream, beyond what the host clock
  and the newest window received explain, or back: a jump or a restart is taken only when
  :attr:`LiveTracker.JUMP_CONFIRM` = 3 consecutive windows agree with each other and with the host
  clock (each advancing in sensor time about as much as the host time between them) over at least
  0.5 s of host time, so neither one window stamped far off nor a burst of forged ones resets the
  tracker or publishes tracks with its stamp; logged at the first and every
  100th); ``windows_subsampled`` and ``events_subsampled`` (a window above the event budget,
  every pixel at 100 Hz: a flash or a crafted window, evenly subsampled to it before the
  pipeline, so tracking stays real-time), ``windows_over_budget`` (one claiming more than 4
  budgets: refused undecoded); windows refused as bad or held are not counted again in ``windows_missed``; gauges ``robots``, ``process_ms`` and ``latency_ms`` (edge publish to
  track publish, host clocks), ``tracker`` and ``detector`` (the method in use: ``fleet`` or
  ``idtrack``, ``default`` or ``paper``).
- Restarts: the fleet tracker's state (:meth:`tracker.fleet.FleetTracker.snapshot`: IDs,
  names, last poses) is written atomically to a small JSON state file every second and at
  exit, and restored at start (unless older than ``--state-max-age``), so track IDs come back
  after a crash, a SIGKILL or an upgrade. The file is validated like a message
  (:func:`check_state`: a regular file (a FIFO or device is never opened blocking), at most
  :data:`MAX_STATE_BYTES`, no key twice in an object, types, finite numbers, ranges, no track ID
  or robot name twice, at most the fleet size's tracks when it is known, else
  :data:`MAX_STATE_TRACKS` = 256); one that is unreadable or invalid in any way is renamed
  ``<file>.bad`` (replacing an older ``.bad``: one is kept), one warning names the problem, and
  the tracker starts afresh. Restored tracks that no detection confirms within the fleet
  tracker's ``lost_s`` (2 s) are no longer published (see :mod:`tracker.fleet`).
- Catching up: a tracker that stalled (its worker blocked, the process stopped, the host
  starved) does not replay its backlog. A window ending more than ``accumulation +``
  :attr:`LiveTracker.STALE_MARGIN_US` (50 ms) before the newest window received is processed but
  its tracks are not published (``tracks_stale``); one ending more than ``accumulation +``
  :attr:`LiveTracker.SKIP_MARGIN_US` (1 s) before it is skipped unprocessed
  (``windows_skipped_stale``; each run of skips is logged with its windows and seconds); after a
  stall the pipeline rebuilds its accumulation window from the windows it keeps before it
  publishes again (tracks not published meanwhile: ``tracks_withheld``).
- Last resort: a window whose processing raises anything unexpected (decode, pipeline,
  publishing, the CSV log) is counted in ``windows_failed``, logged (rate-limited, with the
  exception's type and message) and the loop goes on with the next window.
"""

from __future__ import annotations

import json
import logging
import math
import os
import stat
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import numpy as np
import zenoh

from arena.codec import CodecError, decode
from arena.keys import ALL_GROUNDTRUTH, ALL_ROBOTS, ALL_TELEMETRY, events_key, robot_key, validate_name
from arena.messages import EventWindow, GroundTruthPose, MessageError, Telemetry, Track
from arena.service import Service
from tracker.naming import TelemetryNamer
from tracker.objects import TrackedRobot
from arena.formats.tables import TrackCsvWriter
from tracker.pipeline import Pipeline

log = logging.getLogger("tracker")

__all__ = ["LiveTracker", "Inbox", "run", "default_state_path", "save_state", "load_state", "check_state",
           "MAX_STATE_BYTES", "MAX_STATE_TRACKS"]

#: a state file larger than this is not read (a fleet of 1000 tracks takes ~250 kB)
MAX_STATE_BYTES = 1 << 20
#: at most this many tracks in a state file when the fleet size is unknown (with a known fleet
#: size, at most that many: the fleet tracker keeps no more confirmed or coasting tracks). A lab
#: holds a handful of robots; 256 leaves room for coasting clutter of a long run without a fleet
#: size, and bounds what a crafted file can make the tracker carry and publish
MAX_STATE_TRACKS = 256
#: track IDs in a state file: 0 .. 2**53 (exact in JSON, in a float, in any msgpack int)
MAX_TRACK_ID = 2 ** 53
#: sensor times in a state file: |t| <= 2**62 µs (int64 with room for arithmetic)
MAX_STATE_T_US = 2 ** 62
#: positions in a state file: |x|, |y| <= this, m (as in an arena.messages.Track)
MAX_STATE_POS_M = 1e4
#: a state file written more than this in the future (s) is not restored (the file or the clock is wrong)
STATE_FUTURE_S = 60.0


def default_state_path(name: str) -> Path:
    """``tracker-<name>.json`` in ``$ARENA_STATE_DIR``, systemd's ``$STATE_DIRECTORY`` (the
    unit's ``StateDirectory=``), ``$XDG_STATE_HOME/arena`` or ``~/.local/state/arena``."""
    base = os.environ.get("ARENA_STATE_DIR") or os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    if not base:
        base = str(Path(os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state") / "arena")
    return Path(base) / f"{name}.json"


def save_state(path: Path, state: dict) -> None:
    """Write ``state`` as JSON atomically (a reader or a crash never sees half a file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as fh:
        json.dump(state, fh, separators=(",", ":"))
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _no_duplicate_keys(pairs: list) -> dict:
    """json ``object_pairs_hook``: an object with a key twice is not a state the tracker wrote
    (``json`` would keep the last silently)."""
    out = {}
    for k, v in pairs:
        if k in out:
            raise ValueError(f"the key {k[:40]!r} appears twice in one object")
        out[k] = v
    return out


def load_state(path: Path, camera: str, max_age_s: float, now_s: float | None = None,
               max_tracks: int = MAX_STATE_TRACKS) -> tuple[dict | None, str]:
    """Read a state file written by :func:`save_state` for ``camera``. Returns ``(fleet
    snapshot or None, why)``; raises ValueError (naming the problem) for a file that is not a
    valid tracker state: not a regular file (a FIFO, a device or a directory: opened
    non-blocking, never waited on), larger than :data:`MAX_STATE_BYTES` (not read), not UTF-8
    JSON, an object with a key twice, or refused by :func:`check_state` (``max_tracks``)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        return None, f"no state file {path}: starting afresh"
    except OSError as exc:
        raise ValueError(f"state file {path} cannot be opened ({exc})") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise ValueError(f"state file {path} is not a regular file (a FIFO, device or directory): "
                             "not a tracker state")
        with os.fdopen(fd, "rb") as fh:
            fd = None
            raw = fh.read(MAX_STATE_BYTES + 1)   # bounded: never a whole 1 GB file
    except OSError as exc:
        raise ValueError(f"state file {path} cannot be read ({exc})") from None
    finally:
        if fd is not None:
            os.close(fd)
    if len(raw) > MAX_STATE_BYTES:
        raise ValueError(f"state file {path} is larger than {MAX_STATE_BYTES} bytes: not a tracker state")
    try:
        state = json.loads(raw.decode("utf-8"), object_pairs_hook=_no_duplicate_keys)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:   # JSONDecodeError is a ValueError
        raise ValueError(f"state file {path} is not JSON ({type(exc).__name__}: {str(exc)[:200]})") from None
    try:
        state = check_state(state, max_tracks)
    except ValueError as exc:
        raise ValueError(f"state file {path}: {exc}") from None
    if state["camera"] != camera:
        return None, f"state file {path} is camera {state['camera']!r}'s, not {camera!r}: starting afresh"
    age = (time.time() if now_s is None else now_s) - state["written_s"]
    if age < -STATE_FUTURE_S:
        return None, f"state file {path} was written {-age:.0f} s in the future (a clock was wrong): starting afresh"
    if not age <= max_age_s:
        return None, f"state file {path} is {age:.0f} s old (> {max_age_s:g} s): starting afresh"
    return state["fleet"], f"{age:.1f} s old"


def _num(d: dict, key: str, where: str, *, optional: bool = False, lim: float | None = None) -> None:
    """``d[key]`` must be a finite number (not a bool) with ``|value| <= lim``, or null/absent if ``optional``."""
    v = d.get(key)
    if v is None:
        if optional:
            return
        raise ValueError(f"{where}.{key} is missing or null, expected a number")
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"{where}.{key} is a {type(v).__name__}, expected a number")
    if isinstance(v, int) and abs(v) > 2**1023:   # JSON ints have any size: math.isfinite would overflow
        raise ValueError(f"{where}.{key} is an integer of {len(str(abs(v)))} digits, expected a finite number")
    if not math.isfinite(v):
        raise ValueError(f"{where}.{key} is {v}, expected a finite number")
    if lim is not None and abs(v) > lim:
        raise ValueError(f"{where}.{key} = {v:g} is outside [-{lim:g}, {lim:g}]")


def _int(d: dict, key: str, where: str, lo: int, hi: int, *, optional: bool = False) -> None:
    """``d[key]`` must be an integer (not a bool, not a float) in ``[lo, hi]``, or absent if ``optional``."""
    if key not in d and optional:
        return
    v = d.get(key)
    if isinstance(v, bool) or not isinstance(v, int):
        shown = v if isinstance(v, (int, float)) and not isinstance(v, bool) else type(v).__name__
        raise ValueError(f"{where}.{key} is {shown}, expected an integer")
    if not lo <= v <= hi:
        raise ValueError(f"{where}.{key} = {v} is outside [{lo}, {hi}]")


def check_state(state: object, max_tracks: int = MAX_STATE_TRACKS) -> dict:
    """Validate a decoded tracker state file like a message (pure: no I/O, no clock); returns it
    unchanged or raises ValueError naming the first problem. Checked: a JSON object with a
    ``camera`` name, a finite ``written_s`` (wall clock, s) and a ``fleet`` table of
    :meth:`tracker.fleet.FleetTracker.snapshot` (``v``, ``next_id``, at most ``max_tracks``
    (default :data:`MAX_STATE_TRACKS`; the live tracker passes its fleet size when known)
    ``tracks``, each with an integer ``id`` in ``[0, 2**53]``, no ID and no robot name twice,
    a valid robot name or null, finite ``x``/``y`` (m), ``yaw`` (rad), ``u``/``v`` (px), integer times
    (µs) and ``hits``). Unknown keys are ignored."""
    if not isinstance(state, dict):
        raise ValueError(f"holds a JSON {type(state).__name__}, expected an object: not a tracker state")
    cam = state.get("camera")
    if not isinstance(cam, str):
        raise ValueError(f"'camera' is {type(cam).__name__}, expected a camera name")
    try:
        validate_name(cam, "camera name")
    except ValueError as exc:
        raise ValueError(f"'camera': {exc}") from None
    _num(state, "written_s", "state", lim=1e12)
    fleet = state.get("fleet")
    if not isinstance(fleet, dict):
        raise ValueError(f"'fleet' is {type(fleet).__name__}, expected an object: not a tracker state")
    _int(fleet, "v", "fleet", 0, 1_000_000)
    _int(fleet, "next_id", "fleet", 0, MAX_TRACK_ID, optional=True)
    tracks = fleet.get("tracks")
    if not isinstance(tracks, list):
        raise ValueError(f"fleet.tracks is {type(tracks).__name__}, expected a list")
    if len(tracks) > max_tracks:
        raise ValueError(f"fleet.tracks holds {len(tracks)} tracks, at most {max_tracks}")
    ids: set[int] = set()
    names: set[str] = set()
    for i, rec in enumerate(tracks):
        where = f"fleet.tracks[{i}]"
        if not isinstance(rec, dict):
            raise ValueError(f"{where} is {type(rec).__name__}, expected an object")
        _int(rec, "id", where, 0, MAX_TRACK_ID)
        robot = rec.get("robot")
        if robot is not None:
            if not isinstance(robot, str):
                raise ValueError(f"{where}.robot is {type(robot).__name__}, expected a robot name or null")
            try:
                validate_name(robot, "robot name")
            except ValueError as exc:
                raise ValueError(f"{where}.robot: {exc}") from None
        for k in ("x", "y"):
            _num(rec, k, where, lim=MAX_STATE_POS_M)
        for k in ("vx", "vy"):
            _num(rec, k, where, optional=True, lim=100.0)
        _num(rec, "yaw", where, optional=True, lim=10.0)
        for k in ("u", "v"):
            _num(rec, k, where, optional=True, lim=1e5)
        _int(rec, "t_us", where, -MAX_STATE_T_US, MAX_STATE_T_US)
        _int(rec, "last_seen_us", where, -MAX_STATE_T_US, MAX_STATE_T_US, optional=True)
        _int(rec, "hits", where, 0, 2 ** 31, optional=True)
        if rec["id"] in ids:
            raise ValueError(f"{where}.id = {rec['id']} is another track's ID too")
        ids.add(rec["id"])
        if robot:
            if robot in names:
                raise ValueError(f"{where}.robot {robot!r} is another track's name too (one robot, one track)")
            names.add(robot)
    return state


#: the worker took no window for this long (s): it stalled (or the stream paused); the pipeline
#: rebuilds its accumulation window before it publishes again
STALL_S = 0.5


def _opt(x: float) -> float | None:
    return None if x is None or x != x else float(x)


class LiveTracker:
    """Wraps a :class:`Pipeline` for one camera: decode, order checks, track messages.

    No Zenoh: ``handle(payload, now_ns)`` returns the Track messages to publish (the wiring is in
    :func:`run`); it logs, counts into ``svc``'s status and reads the host clock for timings.
    """

    #: a window this much older than the last one is a restarted stream (e.g. a replay
    #: looping), not a late slice: the pipeline starts afresh (once :attr:`JUMP_CONFIRM` windows agree)
    RESTART_US = 1_000_000
    #: a window starting more than this after the last one, beyond what the host clock has
    #: advanced since (and beyond the newest window received), is a jump ahead: held as
    #: suspicious (``windows_future``) until :attr:`JUMP_CONFIRM` windows agree, µs
    JUMP_US = 1_000_000
    #: a jump of the camera's clock (ahead, or back: a restart) is taken as the new time only when
    #: this many consecutive windows agree on it (each following the previous one by at most
    #: ``JUMP_US``): one window stamped far off (a corrupt or hostile sender) neither resets the
    #: tracker nor publishes tracks with its stamp; the ones before it are counted in
    #: ``windows_future`` or ``windows_past``. A real restart costs the windows of the first ~0.5 s (below)
    JUMP_CONFIRM = 3
    #: ... and only when those windows also agree with the host clock: each follows the previous
    #: one in sensor time by about as much as the host time between them (within
    #: :attr:`JUMP_TOL_US` + :attr:`JUMP_TOL_FRAC` of it; the whole run too), and they span at
    #: least :attr:`JUMP_HOST_SPAN_US` of host time. A burst of forged windows (3, or any number,
    #: sent at once) never passes; a really restarted camera, which streams on continuously, is
    #: taken after ~0.5 s (its windows held meanwhile: not processed, nothing published with their stamps)
    JUMP_TOL_US = 200_000
    JUMP_TOL_FRAC = 0.5
    JUMP_HOST_SPAN_US = 500_000
    #: event budget of a window: at most ``max(W*H, EVENT_BUDGET_FLOOR)`` events per
    #: ``EVENT_BUDGET_PER_US`` (10 ms) of its duration (at most the accumulation time counts), i.e.
    #: every pixel firing at 100 Hz at once (30.7 Mev/s at 640x480, 92 Mev/s at 1280x720). A lab
    #: scene of ground robots makes well under 10 Mev/s; only a flash (lights switched, the camera
    #: knocked) or a crafted window exceeds it, and those carry no robot information: the window is
    #: subsampled deterministically (evenly strided, time order kept) down to the budget
    #: (``windows_subsampled``, ``events_subsampled``) and tracking goes on in real time
    EVENT_BUDGET_PER_US = 10_000
    EVENT_BUDGET_FLOOR = 100_000
    #: ... and a window claiming more than this many budgets (123 Mev/s at 640x480) is not even
    #: decoded (decoding 10 M events costs ~0.3-0.5 s of CPU, a crafted window 9 kB): refused,
    #: ``windows_over_budget``, tracking goes on with the next window
    EVENT_BUDGET_REFUSE = 4
    #: a seq jump by more than this (1000 s of 10 ms windows) is a sequence reset (a restarted or
    #: corrupt sender), counted in ``sequence_resets``, not that many windows missed
    MAX_SEQ_GAP = 100_000

    #: a window ending more than the accumulation time + this before the newest window received
    #: is stale: processed (the fleet keeps its history, the CSV its rows) but its tracks are not
    #: published (``tracks_stale``): what is published is fresh
    STALE_MARGIN_US = 50_000
    #: ... and one ending more than the accumulation time + this before it comes from a stall: it
    #: is skipped unprocessed (``windows_skipped_stale``), so a stalled tracker catches up at once.
    #: Well above a network's hiccups (TCP retransmits stall a lossy link for 0.2-0.5 s), whose
    #: windows are worth processing: skipping them cost a lossy deployment 1-6 % of its MOTA
    SKIP_MARGIN_US = 1_000_000

    #: a ground-truth pose names the nearest track within this distance, m ...
    NAME_GATE_M = 0.10
    #: ... once it has done so this many times in a row
    NAME_VOTES = 5
    #: a ground-truth pose stamped further than this from every track's history (ns) is on
    #: another clock (e.g. a video file's media time): it is matched with the latest tracks
    GT_OTHER_CLOCK_NS = 10_000_000_000

    def __init__(self, pipeline: Pipeline, camera: str, svc=None, make_pipeline=None) -> None:
        self.pipeline = pipeline
        self.make_pipeline = make_pipeline
        self._votes: dict[str, tuple[int, int]] = {}
        self._pending_names: dict[int, str] = {}        # from ground truth (webcam)
        self._pending_tel_names: dict[int, str] = {}    # from telemetry
        self.namer = TelemetryNamer()
        self._namer_now_ns: int | None = None           # host capture time of the newest track fed
        self.camera = camera
        self.unpublished: list[TrackedRobot] = []   # tracks of the last window, if stale: CSV only
        self.sensor_to_host_ns: int | None = None     # of the last window handled (the edge's estimate)
        self.svc = svc
        self.last_seq: int | None = None
        self._last_dropped: int | None = None   # the edge's cumulative drop count in the last window
        self.fleet: dict[str, Track] = {}
        self.lock = threading.Lock()
        w, h = pipeline.calibration.image_size
        self.size = (w, h)
        # catching up: the run of stale windows being skipped
        # [n, first t_start, last t_end, newest t_end, windows the full queue dropped meanwhile]
        self._skipped: list[int] | None = None
        # after a stall or a long skip, tracks are withheld until the pipeline's accumulation
        # window is full again: pending (from the next window processed), then until this end, µs
        self._rebuild_pending = False
        self._rebuild_until: int | None = None
        # windows refused (undecodable) or held (a jump) since the last window whose seq was
        # taken: the next seq gap is not counted as missed for them
        self._refused = 0
        # a run of windows that jumped far from the stream: [n, "future"/"past", last t_end, first t_start]
        self._jump: list | None = None
        self._held_logged = 0              # windows held so far, for rate-limited logging
        self._subsampled = 0               # windows subsampled to the event budget, for logging
        self._over_budget = 0              # windows refused undecoded above EVENT_BUDGET_REFUSE budgets
        self._last_now_ns: int | None = None   # host time when the last window was taken, ns
        # the stream's freshest relation to the host clock: max over the windows taken of their
        # end (sensor µs) - the host time they were taken (µs); reset when the stream restarts
        self._offset_us: int | None = None
        #: windows the worker's queue holds (set by :func:`run`): how far the newest window
        #: received may legitimately be ahead of the last one processed
        self.queue_windows = 100

    def snapshot(self) -> dict | None:
        """The state to write to the state file (None: this tracker keeps none)."""
        snap = getattr(self.pipeline.tracker, "snapshot", None)
        if snap is None:
            return None
        return {"camera": self.camera, "written_s": time.time(), "fleet": snap()}

    def restore(self, fleet: dict) -> list[int]:
        """Bring back a fleet snapshot; returns the restored track IDs (ValueError if unreadable)."""
        restore = getattr(self.pipeline.tracker, "restore", None)
        if restore is None:
            raise ValueError("the idtrack tracker keeps no state")
        return restore(fleet)

    def _count(self, key: str, n: int = 1) -> None:
        if self.svc is not None:
            self.svc.count(key, n)

    def _bad(self, key: str, msg: str) -> None:
        self._count(key)
        if self.svc is not None:
            self.svc.error(msg)
        else:
            log.warning("%s", msg)

    def observe_groundtruth(self, robot: str, x: float, y: float, stamp_us: int | None = None) -> None:
        """A ground-truth pose of ``robot`` (arena m, e.g. from the webcam's markers) captured at
        ``stamp_us`` (host clock, µs): the nearest track within ``NAME_GATE_M`` *at that time*
        (its pose interpolated in its recent history), the same one ``NAME_VOTES`` times in a row,
        gets the robot's name (published on ``arena/robots/<name>`` from then on). A pose stamped
        where the tracks have no history is not used (``groundtruth_out_of_history``), unless it is
        on another clock altogether (:attr:`GT_OTHER_CLOCK_NS` away: matched with the latest
        tracks); without a stamp, the latest tracks are used. Thread-safe; applied by the worker
        at its next window."""
        try:
            validate_name(robot, "robot name")
        except ValueError:
            return
        with self.lock:
            candidates = [m for m in self.fleet.values() if m.state != "tentative"]
            poses = {m.track_id: (m.x, m.y) for m in candidates}
            newest = self._namer_now_ns
            if stamp_us is not None and newest is not None and abs(stamp_us * 1000 - newest) <= self.GT_OTHER_CLOCK_NS:
                t_ns = int(stamp_us) * 1000
                poses = {}
                for m in candidates:
                    p = self.namer.track_position_at(m.track_id, t_ns)
                    if p is not None:
                        poses[m.track_id] = p
                if not poses:
                    self._count("groundtruth_out_of_history")
                    return
            best, best_d = None, self.NAME_GATE_M
            for tid, (tx, ty) in poses.items():
                d = ((tx - x) ** 2 + (ty - y) ** 2) ** 0.5
                if d <= best_d:
                    best, best_d = tid, d
            if best is None:
                self._votes.pop(robot, None)
                return
            tid, n = self._votes.get(robot, (best, 0))
            n = n + 1 if tid == best else 1
            self._votes[robot] = (best, n)
            if n >= self.NAME_VOTES and not any(m.track_id == best and m.robot == robot for m in self.fleet.values()):
                self._pending_names[best] = robot

    def observe_telemetry(self, msg: Telemetry) -> None:
        """A telemetry sample of a robot (``arena/telemetry/<robot>``): fed to the
        :class:`~tracker.naming.TelemetryNamer`. Thread-safe."""
        try:
            validate_name(msg.robot, "robot name")
        except ValueError:
            return
        gz = msg.gyro[2] if len(msg.gyro) == 3 else math.nan
        with self.lock:
            self.namer.add_telemetry(msg.robot, msg.robot_time_us, msg.host_time_ns, msg.speed_left,
                                     msg.speed_right, float(gz))

    def _apply_names(self) -> None:
        """Give tracks the names found since the last window (worker thread)."""
        with self.lock:
            pending, self._pending_names = self._pending_names, {}
            tel, self._pending_tel_names = self._pending_tel_names, {}
            current = {m.track_id: m.robot for m in self.fleet.values()}
        namer = getattr(self.pipeline.tracker, "set_robot_name", None)
        if namer is None:
            return
        for source, names in (("names_from_telemetry", tel), ("names_from_groundtruth", pending)):
            for tid, robot in names.items():
                if current.get(tid) == robot:
                    continue
                if namer(tid, robot):
                    self._count(source)
                    log.info("camera %s: track %d is robot %s (from %s)", self.camera, tid, robot,
                             source.split("_")[-1])

    def _feed_namer(self, out: list, now_ns: int, win_end_us: int) -> None:
        """Feed this window's tracks to the telemetry namer; evaluate it (every 0.25 s of data)."""
        with self.lock:
            newest = None
            for _, msg, _ in out:
                if msg.state == "tentative":
                    continue
                host = msg.host_ns if msg.host_ns is not None else now_ns - (win_end_us - msg.stamp_us) * 1000
                self.namer.add_track(msg.track_id, host, msg.x, msg.y, msg.yaw, msg.vx, msg.vy,
                                     stamp_us=msg.stamp_us)
                newest = host if newest is None else max(newest, host)
            if newest is None:
                return
            self._namer_now_ns = newest if self._namer_now_ns is None else max(self._namer_now_ns, newest)
            found = self.namer.update(self._namer_now_ns)
            self._pending_tel_names.update(found)

    def window_end(self, payload: bytes, now_ns: int | None = None) -> int | None:
        """End (sensor µs) of the window in ``payload`` if it is a valid window of this camera and
        sensor, else None (the worker peeks at the newest window received with it). With
        ``now_ns`` (host clock), also None for a window further ahead of the last one processed
        than the queue's span, the host time since and :attr:`JUMP_US` allow: a window stamped
        far in the future must not make the windows queued before it look stale."""
        try:
            win = EventWindow.decode(payload)
        except MessageError:
            return None
        if win.camera != self.camera or (win.width, win.height) != self.size:
            return None
        last = self.pipeline.last_t_us
        if now_ns is not None and last is not None:
            span = max(0, win.t_end_us - win.t_start_us) * max(1, self.queue_windows)
            if self._beyond_stream_us(win.t_end_us, now_ns) > self.JUMP_US + span:
                return None
        return win.t_end_us

    def _beyond_stream_us(self, t_us: int, now_ns: int | None) -> int:
        """How far (µs) sensor time ``t_us`` is ahead of where the stream is now by the host
        clock: the stream's freshest relation to the host clock (the largest ``t_end - host``
        of the windows taken, host time never going back) carried to ``now_ns``. A backlog
        delivered late (a stalled worker, a congested link, a full queue dropping windows)
        only lags that relation; a window stamped in the future leads it. Without a window
        taken yet: ahead of the pipeline's last time."""
        last = self.pipeline.last_t_us
        if self._offset_us is None or now_ns is None:
            return int(t_us) - (last if last is not None else int(t_us))
        now_us = max(int(now_ns), self._last_now_ns or int(now_ns)) // 1000
        return int(t_us) - (now_us + self._offset_us)

    def _held_jump(self, win: EventWindow, now_ns: int, newest_end_us: int | None) -> bool:
        """Whether ``win`` is held (not processed) because it jumped far from the stream: it
        starts more than :attr:`JUMP_US` after the last window beyond what the host clock
        advanced since and beyond the newest window received (``windows_future``), or ends more
        than :attr:`RESTART_US` before it (``windows_past``), and fewer than
        :attr:`JUMP_CONFIRM` consecutive windows agree on that jump yet. The window that makes
        them agree is taken (a restart: :meth:`_in_order` starts afresh)."""
        last = self.pipeline.last_t_us
        kind = None
        if last is not None:
            if (self._beyond_stream_us(win.t_start_us, now_ns) > self.JUMP_US
                    and not (newest_end_us is not None and win.t_end_us <= newest_end_us)):
                kind = "future"
            elif win.t_end_us < last - self.RESTART_US and self.make_pipeline is not None:
                kind = "past"
        run = self._jump
        if kind is None:
            self._jump = None   # the stream goes on: whatever jumped was a stray window
            return False
        now_us = int(now_ns) // 1000
        if (run is not None and run[1] == kind and run[2] < win.t_end_us <= run[2] + self.JUMP_US
                and self._agrees_with_host(win.t_end_us - run[2], now_us - run[5])):
            run[0] += 1
            run[2] = win.t_end_us
            run[5] = now_us
        else:
            # [n, kind, last t_end, first t_start, first t_end, host µs of the last, host µs of the first]
            run = self._jump = [1, kind, win.t_end_us, win.t_start_us, win.t_end_us, now_us, now_us]
        host_span = run[5] - run[6]
        if (run[0] >= self.JUMP_CONFIRM and host_span >= self.JUMP_HOST_SPAN_US
                and self._agrees_with_host(run[2] - run[4], host_span)):
            self._jump = None
            log.warning("camera %s: %d consecutive windows over %.2f s of host time agree that its clock jumped %s "
                        "(%d µs after %d µs): taken as the new time", self.camera, run[0], host_span / 1e6,
                        "ahead" if kind == "future" else "back", run[3], last)
            return False
        key = "windows_future" if kind == "future" else "windows_past"
        self._count(key)
        self._held_logged += 1
        if self._held_logged == 1 or self._held_logged % 100 == 0:
            log.warning("camera %s: window seq %d (%d..%d µs) jumped %s from the stream (last window ended %d µs): "
                        "held, not processed (counted in %s, %d so far); a jump is taken only when %d consecutive "
                        "windows agree, with each other and with the host clock, over %.1f s",
                        self.camera, win.seq, win.t_start_us, win.t_end_us,
                        "ahead" if kind == "future" else "back", last, key, self._held_logged, self.JUMP_CONFIRM,
                        self.JUMP_HOST_SPAN_US / 1e6)
        return True

    def _agrees_with_host(self, sensor_us: int, host_us: int) -> bool:
        """Whether a sensor-time advance agrees with the host time over the same windows (within
        :attr:`JUMP_TOL_US` + :attr:`JUMP_TOL_FRAC` of the host time); host time going back never does."""
        if host_us < 0:
            return False
        return abs(sensor_us - host_us) <= self.JUMP_TOL_US + self.JUMP_TOL_FRAC * host_us

    def _end_skip_run(self) -> None:
        n, t0, t1, newest, queue = self._skipped
        self._skipped = None
        log.warning("camera %s: caught up: skipped %d stale window(s), %.2f s of sensor time (%d..%d µs), "
                    "ending more than %.0f ms before the newest window received (%d µs)%s", self.camera, n,
                    (t1 - t0) / 1e6, t0, t1, (self.pipeline.accumulation_us + self.STALE_MARGIN_US) / 1e3, newest,
                    f"; the full queue dropped {queue} older one(s)" if queue else "")

    def handle(self, payload: bytes, now_ns: int, dropped_in_queue: int = 0, newest_end_us: int | None = None,
               resumed: bool = False) -> list[tuple[str, Track, TrackedRobot]]:
        """Process one event-window payload; returns ``(key, message, track)`` to publish.
        ``dropped_in_queue``: windows our own full queue dropped since the previous call.
        ``newest_end_us``: end (sensor µs) of the newest window received (waiting in the queue):
        this window is skipped if it ends more than ``accumulation + STALE_MARGIN_US`` before it.
        ``resumed``: the worker has just come back from a stall (no window for a while): the
        tracks are withheld until the pipeline's accumulation window is full again."""
        self.unpublished = []   # tracks of a stale window: for the CSV, not to publish
        if resumed:
            self._rebuild_pending = True
        self._apply_names()
        decoded = self._decode_window(payload)
        if decoded is None:
            return []
        win, events = decoded
        if self._held_jump(win, now_ns, newest_end_us):
            self._refused += 1
            return []
        if not self._in_order(win):
            return []
        self._count_seq_gap(win, now_ns, dropped_in_queue)
        self._refused = 0
        self._last_now_ns = max(int(now_ns), self._last_now_ns or int(now_ns))   # host time never going back
        off = int(win.t_end_us) - self._last_now_ns // 1000
        self._offset_us = off if self._offset_us is None else max(self._offset_us, off)
        self.last_seq = win.seq
        self.sensor_to_host_ns = win.sensor_to_host_ns
        self._last_dropped = win.dropped
        acc = self.pipeline.accumulation_us
        stale = newest_end_us is not None and win.t_end_us < newest_end_us - acc - self.STALE_MARGIN_US
        if self._skip_stalled(win, newest_end_us, dropped_in_queue, acc):
            return []
        if not self._events_fit(win, events):
            return []
        events = self._within_budget(win, events, acc)
        t0 = time.perf_counter()
        try:
            tracks = self.pipeline.push(events, win.t_end_us)
        except ValueError as exc:
            self._bad("windows_bad", f"window seq {win.seq} skipped: {exc}")
            return []
        self._count("windows_in")
        if self.svc is not None:
            self.svc.gauge("process_ms", round((time.perf_counter() - t0) * 1e3, 3))
        if self._withheld_while_rebuilding(win, tracks, acc):
            return []
        out = self._track_messages(tracks, win, now_ns)
        with self.lock:
            self.fleet = {k: m for k, m, _ in out}
        self._feed_namer(out, now_ns, win.t_end_us)
        if stale:   # processed, logged to the CSV by the worker, not published
            self._count("tracks_stale", len(out))
            self.unpublished = [tr for _, _, tr in out]
            return []
        return out

    def _decode_window(self, payload: bytes):
        """``(window, events)`` decoded from ``payload``, or None (counted in ``windows_bad``)
        if it is corrupt, of another camera or of another sensor size than the calibration's."""
        try:
            win = EventWindow.decode(payload)
            if win.camera != self.camera:
                raise MessageError(f"window of camera {win.camera!r} on {self.camera!r}'s key")
            if (win.width, win.height) != self.size:
                raise MessageError(f"window is {win.width}x{win.height} px but the calibration is "
                                   f"{self.size[0]}x{self.size[1]} px")
            budget = self.event_budget(win, self.pipeline.accumulation_us)
            if win.count > self.EVENT_BUDGET_REFUSE * budget:
                self._count("windows_over_budget")
                self._refused += 1   # counted here: not again as missed in the next seq gap
                self._over_budget += 1
                if self._over_budget == 1 or self._over_budget % 100 == 0:
                    log.warning("camera %s: window seq %d claims %d events in %d µs, more than %d x the event "
                                "budget of %d: refused undecoded (counted in windows_over_budget, %d so far)",
                                self.camera, win.seq, win.count, win.t_end_us - win.t_start_us,
                                self.EVENT_BUDGET_REFUSE, budget, self._over_budget)
                return None
            events = decode(win.codec, bytes(win.data), win.count)
        except (MessageError, CodecError) as exc:
            self._bad("windows_bad", f"corrupt event window skipped: {exc}")
            self._refused += 1   # counted here: not again as missed in the next seq gap
            return None
        return win, events

    def _in_order(self, win: EventWindow) -> bool:
        """Whether ``win`` comes after the last window processed. A window far older than it
        is a restarted stream: the pipeline starts afresh (``stream_restarts``) and it is in
        order; one slightly older or as old is late: skipped (``windows_late``)."""
        last = self.pipeline.last_t_us
        if last is not None and win.t_end_us < last - self.RESTART_US and self.make_pipeline is not None:
            self._count("stream_restarts")
            log.warning("camera %s restarted its clock (%d µs after %d µs): tracking afresh",
                        self.camera, win.t_end_us, last)
            self.pipeline = self.make_pipeline()
            self.last_seq = self._last_dropped = self._offset_us = None
            last = None
        if last is not None and win.t_end_us <= last:
            self._bad("windows_late", f"out-of-order window seq {win.seq} (ends {win.t_end_us} µs, "
                                      f"last {last} µs) skipped")
            return False
        return True

    def _count_seq_gap(self, win: EventWindow, now_ns: int, dropped_in_queue: int) -> None:
        """Account for the windows missing before ``win`` (by its seq): a huge jump is a
        sequence reset; the rest were dropped by the edge (by its own count), by our full
        queue (``dropped_in_queue``), or lost on the way (``windows_missed``)."""
        if self.last_seq is not None and win.seq > self.last_seq + 1 + self.MAX_SEQ_GAP:
            self._count("sequence_resets")
            log.warning("camera %s: seq jumped from %d to %d: counted as a sequence reset, not as missed windows",
                        self.camera, self.last_seq, win.seq)
        elif self.last_seq is not None and win.seq > self.last_seq + 1:
            # windows refused as bad (their seq unreadable or untrusted) or held since the last
            # one are already counted (windows_bad, windows_future, ...): not missed
            gap = win.seq - self.last_seq - 1 - min(win.seq - self.last_seq - 1, self._refused)
            if gap <= 0:
                return
            # windows the edge itself dropped (its cumulative ``dropped`` grew by as many) are
            # the edge's count; the rest were lost on the way or in our own queue
            at_edge = min(gap, max(0, win.dropped - self._last_dropped)) if self._last_dropped is not None else 0
            if at_edge:
                self._count("windows_dropped_at_edge", at_edge)
            here = min(gap - at_edge, dropped_in_queue)
            if here:
                log.warning("camera %s: tracker queue full, %d window(s) before seq %d dropped",
                            self.camera, here, win.seq)
            if gap - at_edge - here:
                self._count("windows_missed", gap - at_edge - here)
                waited = (now_ns - win.publish_ns) / 1e6 if win.publish_ns else float("nan")
                log.warning("camera %s: %d window(s) before seq %d lost on the way (neither the edge nor "
                            "our queue dropped them); this one was published %.0f ms ago",
                            self.camera, gap - at_edge - here, win.seq, waited)

    def _skip_stalled(self, win: EventWindow, newest_end_us: int | None, dropped_in_queue: int, acc: int) -> bool:
        """Whether to skip ``win`` unprocessed because it ends more than the accumulation time
        + ``SKIP_MARGIN_US`` before the newest window received (a stalled tracker catching up;
        ``windows_skipped_stale``, logged once per run of them). At the first window after such
        a run, the run is logged, and if it spanned a whole accumulation window, the tracks are
        withheld until that is full again. ``acc``: the pipeline's accumulation time, µs."""
        if newest_end_us is not None and win.t_end_us < newest_end_us - acc - self.SKIP_MARGIN_US:
            self._count("windows_skipped_stale")
            if self._skipped is None:
                self._skipped = [0, win.t_start_us, win.t_end_us, newest_end_us, 0]
            self._skipped[0] += 1
            self._skipped[2:4] = [win.t_end_us, newest_end_us]
            self._skipped[4] += dropped_in_queue
            return True
        if self._skipped is not None:
            if self._skipped[2] - self._skipped[1] >= acc:
                self._rebuild_pending = True   # the accumulation window lost its history: rebuild it first
            self._end_skip_run()
        return False

    def _events_fit(self, win: EventWindow, events: np.ndarray) -> bool:
        """Whether ``win``'s events all precede its end (else it is skipped, ``windows_bad``);
        those before its start are counted (``events_late``) and processed."""
        if events.size:
            # the edge's Slicer (arena.slicing) puts a late event into the window open when it came,
            # so events may precede t_start (counted, processed as offline) but never reach t_end
            if int(events["t"].max()) >= win.t_end_us:
                self._bad("windows_bad", f"window seq {win.seq} has events at or after its end: skipped")
                return False
            late = int(np.count_nonzero(events["t"] < win.t_start_us))
            if late:
                self._count("events_late", late)
        return True

    def event_budget(self, win: EventWindow, acc: int) -> int:
        """Most events of ``win`` fed to the pipeline: ``max(W*H, EVENT_BUDGET_FLOOR)`` per
        ``EVENT_BUDGET_PER_US`` of its duration, counted at least one such period and at most the
        accumulation time ``acc`` (a window claiming a long span gains nothing beyond what the
        pipeline keeps)."""
        w, h = self.size
        per = max(w * h, self.EVENT_BUDGET_FLOOR)
        dur = min(max(int(win.t_end_us) - int(win.t_start_us), self.EVENT_BUDGET_PER_US), max(int(acc), 1))
        dur = max(dur, 1)
        return max(1, (per * dur) // self.EVENT_BUDGET_PER_US)

    def _within_budget(self, win: EventWindow, events: np.ndarray, acc: int) -> np.ndarray:
        """``events``, or if they exceed :meth:`event_budget` (a flash or a crafted window: above
        any sensor's rate in normal operation), an evenly strided subset of exactly the budget
        (deterministic, time order kept), counted in ``windows_subsampled`` and
        ``events_subsampled`` and logged at the first and every 100th."""
        budget = self.event_budget(win, acc)
        n = int(events.size)
        if n <= budget:
            return events
        keep = (np.arange(budget, dtype=np.int64) * n) // budget
        out = events[keep]
        self._count("windows_subsampled")
        self._count("events_subsampled", n - budget)
        self._subsampled += 1
        if self._subsampled == 1 or self._subsampled % 100 == 0:
            log.warning("camera %s: window seq %d holds %d events in %d µs, above the budget of %d (every pixel "
                        "at 100 Hz): subsampled to %d (a flash or a crafted window; %d window(s) so far)",
                        self.camera, win.seq, n, win.t_end_us - win.t_start_us, budget, budget, self._subsampled)
        return out

    def _withheld_while_rebuilding(self, win: EventWindow, tracks: list, acc: int) -> bool:
        """Whether ``win``'s tracks are withheld (``tracks_withheld``) because the pipeline's
        accumulation window is being rebuilt after a stall or a long skip."""
        if self._rebuild_pending:
            self._rebuild_pending, self._rebuild_until = False, win.t_start_us + acc
        if self._rebuild_until is not None:
            if win.t_end_us < self._rebuild_until:
                self._count("tracks_withheld", len(tracks))
                return True
            self._rebuild_until = None
        return False

    def _track_messages(self, tracks: list, win: EventWindow, now_ns: int) -> list[tuple[str, Track, TrackedRobot]]:
        """``(key, Track message, track)`` for each track of ``win``, with its timings."""
        out = []
        for tr in tracks:
            msg = Track(track_id=tr.track_id, robot=tr.robot, camera=self.camera, stamp_us=tr.t_us,
                        x=float(tr.x), y=float(tr.y), yaw=_opt(tr.yaw), vx=_opt(tr.vx), vy=_opt(tr.vy),
                        u_px=_opt(tr.u), v_px=_opt(tr.v), state=tr.state, n_events=int(tr.n_events),
                        window_end_us=win.t_end_us, edge_publish_ns=win.publish_ns or None,
                        tracker_publish_ns=now_ns,
                        host_ns=None if win.sensor_to_host_ns is None else tr.t_us * 1000 + win.sensor_to_host_ns)
            out.append((robot_key(tr.robot or tr.track_id), msg, tr))
        return out


def run(session: zenoh.Session, make_pipeline: Callable[[], Pipeline], camera: str, stop: threading.Event, *,
        name: str, pipeline: Pipeline | None = None, tracker: str = "fleet", detector: str = "default",
        queue: int = 100, names_from_groundtruth: bool = True, names_from_telemetry: bool = True, state_path: Path | None = None,
        state_max_age_s: float = 600.0, writer: TrackCsvWriter | None = None,
        duration_s: float | None = None) -> None:
    """Track ``arena/events/<camera>`` on ``session`` until ``stop`` is set (or ``duration_s``
    passes): publish ``arena/robots/<id>``, answer ``get("arena/robots/*")``, report as service
    ``tracker/<name>``.

    Built objects only (``tracker.cli`` turns flags and the lab file into them):
    ``make_pipeline()`` builds a fresh :class:`~tracker.pipeline.Pipeline` (after a restarted
    stream); ``pipeline`` is the first one (default: ``make_pipeline()``); ``tracker`` and
    ``detector`` are the names of the method, shown by ``arena status``; ``names_from_telemetry``,
    ``names_from_groundtruth``: name tracks from ``arena/telemetry/*``, ``arena/groundtruth/*``;
    ``state_path``: the fleet
    state file read at start and written every second (None: none); ``writer``: a CSV log of
    every track (stale ones too)."""
    pipe = make_pipeline() if pipeline is None else pipeline
    deadline = None if duration_s is None else time.monotonic() + duration_s
    with Service(session, "tracker", name) as svc:
        live = LiveTracker(pipe, camera, svc, make_pipeline)
        live.queue_windows = max(1, queue)
        # the method in use, shown by `arena status` (it may come from the lab's [services.tracker])
        svc.gauge("tracker", tracker)
        svc.gauge("detector", detector)
        if state_path is not None:
            _restore_state(live, state_path, state_max_age_s, svc)
        next_save = time.monotonic() + 1.0
        publishers: dict[str, zenoh.Publisher] = {}
        queryable, gt_sub, tel_sub = _declare_inputs(session, live, svc, names_from_groundtruth,
                                                     names_from_telemetry)
        inbox = Inbox(max(1, queue))
        sub = session.declare_subscriber(events_key(camera), lambda sample: inbox.put(sample.payload.to_bytes()))
        log.info("tracking %s (%s tracker, %s detector) -> arena/robots/*", events_key(camera), tracker, detector)
        try:
            newest: tuple[bytes | None, int | None] = (None, None)   # (payload, its window end), cached
            last_window = None   # monotonic s when the worker last took a window
            while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
                if state_path is not None and time.monotonic() >= next_save:
                    next_save = time.monotonic() + 1.0
                    _save_state(live, state_path, svc)
                payload, dropped = inbox.get(timeout=0.2)
                if dropped:
                    svc.count("windows_dropped_in_queue", dropped)
                if payload is None:
                    continue
                now = time.monotonic()
                resumed = last_window is not None and now - last_window > STALL_S
                last_window = now
                try:
                    queued = inbox.newest()
                    if queued is not None and queued is not newest[0]:
                        newest = (queued, live.window_end(queued, time.time_ns()))
                    out = live.handle(payload, time.time_ns(), dropped,
                                      newest_end_us=newest[1] if queued is not None else None, resumed=resumed)
                    _publish(session, publishers, out, live, svc, writer)
                except Exception as exc:   # last resort: one window must not stop the tracker
                    svc.count("windows_failed")
                    svc.error(f"window not processed ({type(exc).__name__}: {str(exc)[:300]}); "
                              "counted in windows_failed, tracking goes on")
                    log.debug("window not processed", exc_info=True)
        except KeyboardInterrupt:
            pass
        finally:
            if state_path is not None:
                _save_state(live, state_path, svc)
            sub.undeclare()
            queryable.undeclare()
            if gt_sub is not None:
                gt_sub.undeclare()
            if tel_sub is not None:
                tel_sub.undeclare()
            for pub in publishers.values():
                pub.undeclare()


def _declare_inputs(session: zenoh.Session, live: LiveTracker, svc, names_from_groundtruth: bool,
                    names_from_telemetry: bool):
    """Declare what the tracker answers and listens to besides its event windows: the
    ``get("arena/robots/*")`` queryable (the latest fleet), and, if asked, the subscribers
    to ground truth and telemetry that name tracks (a bad message is counted, not raised).
    Returns ``(queryable, groundtruth subscriber or None, telemetry subscriber or None)``."""
    def on_query(query: zenoh.Query) -> None:
        with live.lock:
            fleet = list(live.fleet.items())
        for key, msg in fleet:
            if zenoh.KeyExpr(key).intersects(query.key_expr):
                query.reply(key, msg.encode())

    def on_groundtruth(sample) -> None:
        try:
            gt = GroundTruthPose.decode(sample.payload.to_bytes())
        except MessageError:
            svc.count("groundtruth_bad")
            return
        live.observe_groundtruth(gt.robot, gt.x, gt.y, gt.stamp_us)

    def on_telemetry(sample) -> None:
        try:
            tel = Telemetry.decode(sample.payload.to_bytes())
        except MessageError:
            svc.count("telemetry_bad")
            return
        live.observe_telemetry(tel)

    queryable = session.declare_queryable(ALL_ROBOTS, on_query)
    gt_sub = (session.declare_subscriber(ALL_GROUNDTRUTH, on_groundtruth)
              if names_from_groundtruth else None)
    tel_sub = (session.declare_subscriber(ALL_TELEMETRY, on_telemetry)
               if names_from_telemetry else None)
    svc.count("names_from_telemetry", 0)
    svc.count("names_from_groundtruth", 0)
    return queryable, gt_sub, tel_sub


def _publish(session: zenoh.Session, publishers: dict, out: list, live: LiveTracker, svc,
             writer: TrackCsvWriter | None) -> None:
    """Publish the tracks of one window (declaring a publisher per robot key on first use,
    stamped with the publish time), gauge the robots and the edge-to-track latency, and log
    every track, published or stale, to ``writer``."""
    for key, msg, tr in out:
        pub = publishers.get(key)
        if pub is None:
            pub = publishers[key] = session.declare_publisher(key)
        msg.tracker_publish_ns = time.time_ns()
        pub.put(msg.encode())
    if out:
        svc.count("tracks_out", len(out))
        svc.gauge("robots", sum(1 for _, m, _ in out if m.state != "tentative"))
        edge = out[0][1].edge_publish_ns
        if edge:
            svc.gauge("latency_ms", round((time.time_ns() - edge) / 1e6, 3))
        if writer is not None:
            writer.write((tr for _, _, tr in out), live.sensor_to_host_ns)
    if live.unpublished and writer is not None:   # stale: logged, not published
        writer.write(live.unpublished, live.sensor_to_host_ns)


class Inbox:
    """Bounded FIFO between Zenoh's callback thread and the worker: when full, the oldest item
    is dropped and counted (a lagging tracker catches up on fresh data), and the worker sleeps
    until an item arrives (polling a ``RingChannel`` woke it a thousand times a second)."""

    def __init__(self, size: int):
        self.size = int(size)
        self._items: deque = deque()
        self._dropped = 0
        self._cv = threading.Condition()

    def put(self, item) -> None:
        with self._cv:
            if len(self._items) >= self.size:
                self._items.popleft()
                self._dropped += 1
            self._items.append(item)
            self._cv.notify()

    def newest(self):
        """The newest item waiting (None if none), left in place."""
        with self._cv:
            return self._items[-1] if self._items else None

    def get(self, timeout: float) -> tuple[object | None, int]:
        """The oldest item (None after ``timeout`` s without one) and how many were dropped
        since the previous call."""
        with self._cv:
            if not self._items:
                self._cv.wait(timeout)
            item = self._items.popleft() if self._items else None
            dropped, self._dropped = self._dropped, 0
            return item, dropped


def _restore_state(live: LiveTracker, path: Path, max_age_s: float, svc) -> None:
    """Restore the fleet from ``path``; a file that is not a valid state (any problem) is
    renamed ``<file>.bad`` (one kept: it replaces an older one), one warning names the problem,
    and the tracker starts afresh."""
    cap = getattr(getattr(live.pipeline.tracker, "config", None), "fleet_size", None)
    try:
        fleet, why = load_state(path, live.camera, max_age_s,
                                max_tracks=MAX_STATE_TRACKS if cap is None else min(int(cap), MAX_STATE_TRACKS))
        if fleet is None:
            log.info("%s", why)
            return
        ids = live.restore(fleet)
    except (ValueError, TypeError, OverflowError) as exc:   # restore's own checks as a second line
        bad = path.with_name(path.name + ".bad")
        try:
            os.replace(path, bad)
            aside = f"renamed {bad.name} (inspect or delete it)"
        except OSError as err:
            aside = f"and cannot be renamed {bad.name} ({err}); it is overwritten at the next save"
        svc.count("state_rejected")
        svc.error(f"{exc}; {aside}, starting afresh")
        return
    svc.count("state_restored")
    log.info("restored %d track(s) %s from %s (%s)", len(ids), ids, path, why)


def _save_state(live: LiveTracker, path: Path, svc) -> None:
    state = live.snapshot()
    if state is None:
        return
    try:
        save_state(path, state)
    except (OSError, ValueError, TypeError) as exc:
        svc.count("state_write_errors")
        log.warning("cannot write the state file %s: %s", path, exc)
