"""Records shared by the trackers: what goes in (observations) and what comes out (tracks).

Both are in the arena frame (metres, m/s, yaw in rad counter-clockwise from +x) with the
sensor-frame pixel position kept alongside (u column right, v row down, px).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# the track states are part of the Track message's contract: one definition, in arena/ (re-exported)
from arena.messages import COASTING, CONFIRMED, TENTATIVE

__all__ = ["Observation", "TrackedRobot", "TENTATIVE", "CONFIRMED", "COASTING"]


@dataclass
class Observation:
    """One detection in the arena frame.

    Attributes:
        x, y: position, m, at ``t_us``.
        t_us: time of the position, µs (input clock).
        vx, vy: velocity, m/s (NaN when unknown), estimated at ``t_vel_us``.
        speed_sigma: 1-sigma uncertainty of the velocity, m/s (NaN when unknown).
        yaw: heading, rad (NaN when unknown), at ``t_vel_us``.
        yaw_source: ``"motion"``, ``"polarity"`` or ``""``.
        u, v: position in the sensor frame, px.
        n_events: events in the cluster.
        t_vel_us: time the velocity and the heading refer to (the cluster's mean event time), µs.
        shape_yaw: orientation of the cluster's shape, rad, known modulo 2*pi/``shape_order``
            (NaN when unknown), at ``t_vel_us``.
        shape_order: rotational symmetry of the footprint (4: square, 2: rectangle).
        t_act_us: end of the cluster's activity, µs (None: ``t_us``); well before ``t_us``
            when the robot stopped inside the window (no events since: it is at rest).
        whole: True when the detection covers the whole robot: its leading and trailing edges
            grouped (a plain shell shows only those), or one filled cluster as long and wide as
            the chassis. False for a part: a lone edge bar (the robot placed half a chassis
            behind or ahead of it, by the prediction) or a sparse cluster; its position is less
            certain and ``shape_yaw`` is NaN. Default True (the behaviour before the field).
    """

    x: float
    y: float
    t_us: int
    vx: float = math.nan
    vy: float = math.nan
    speed_sigma: float = math.nan
    yaw: float = math.nan
    yaw_source: str = ""
    u: float = math.nan
    v: float = math.nan
    n_events: int = 0
    t_vel_us: int | None = None
    shape_yaw: float = math.nan
    shape_order: int = 4
    t_act_us: int | None = None
    whole: bool = True


@dataclass
class TrackedRobot:
    """A track as the trackers report it (one per track per update).

    Attributes:
        track_id: stable integer id (1, 2, ...).
        x, y: position, m; vx, vy: velocity, m/s; yaw: rad CCW from +x (NaN when unknown).
        t_us: time the pose refers to, µs.
        state: ``tentative``, ``confirmed`` or ``coasting`` (not detected in this update).
        age: updates since the track was born; hits: updates with a detection;
        misses: consecutive updates without one.
        u, v: last sensor position, px; n_events: events of the last detection (0 when coasting).
        robot: robot name when known, else None.
    """

    track_id: int
    x: float
    y: float
    t_us: int
    vx: float = math.nan
    vy: float = math.nan
    yaw: float = math.nan
    state: str = CONFIRMED
    age: int = 0
    hits: int = 0
    misses: int = 0
    u: float = math.nan
    v: float = math.nan
    n_events: int = 0
    robot: str | None = None
