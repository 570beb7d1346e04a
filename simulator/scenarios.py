"""Built-in scenarios: N robots driving the paper's patterns, recorded with exact truth.

>>> rec = generate(Scenario(n_robots=2, pattern="circle", power=0.5, duration_s=2.0))
>>> rec.events["t"][:3], rec.truth[:2], rec.first_motion_us()

A :class:`Recording` carries the events (sensor frame, µs), a signal/noise label per
event, the truth poses (arena frame, >= 200 Hz), the robot names and the camera
calibration, so a tracker can be run and scored offline.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from simulator.autopilot import PATTERNS, Autopilot, make_plans
from simulator.camera import BODIES, NADIR_OFFSET_M, CeilingCamera
from simulator.dvs import DvsParams
from simulator.simulation import TRUTH_DTYPE, Simulation
from simulator.world import (LIGHTING_LEVELS, RobotSpec, World, _is_int, _is_real, check_bool, check_choice,
                             check_number)

#: Default shell colours, cycled over robots: (name, sRGB). Black gives dense events,
#: yellow and white-ish sparse ones (close to the white mats).
COLOURS: list[tuple[str, tuple[int, int, int]]] = [
    ("black", (25, 25, 25)), ("yellow", (240, 215, 30)), ("red", (200, 35, 35)),
    ("blue", (35, 75, 200)), ("green", (40, 160, 70)), ("white", (225, 225, 220)),
    ("orange", (240, 120, 25)), ("purple", (120, 45, 150)),
]


@dataclass
class Scenario:
    """What to simulate.

    Attributes:
        n_robots: number of robots (0-16 is the tested range).
        pattern: one of ``circle, square, stopgo, cross, figure8, still``.
        power: motor power as a fraction of full (the paper: 0.5 or 1.0).
        duration_s: simulated duration, s.
        lighting: ``full``, ``dimmed`` or ``dark``.
        seed: seed of everything (physics, sensor, noise).
        width, height: event sensor size, px.
        colours: shell colours (sRGB) per robot; default cycles :data:`COLOURS`.
        markers: print ArUco ids 0..n-1 on the shells (off by default: real robots are plain
            shells; a lab may add markers for the webcam).
        stagger_s: robot i starts moving at 0.2 + stagger_s * i s.
        dvs: pixel-model parameters (None: defaults).
        arena_m: arena side, m.
        body: robot body model, ``"3d"`` (blade, treads, shell as boxes, ray-traced) or
            ``"flat"`` (the shell top as a plate); see :func:`simulator.camera.robot_body`.
        shadow: soft contact shadow on the mat around each robot.
        camera_height_m: lens height above the mats, m.
        nadir_offset_m: (dx, dy) of the point under the lens from the arena centre, m.
        spin_dps: zero-point turn rate at full power, deg/s, with tread scrubbing (real
            tracked robots: ~150; ~75 at half power); None: no scrubbing (ideal skid kinematics).
    """

    n_robots: int = 1
    pattern: str = "circle"
    power: float = 1.0
    duration_s: float = 5.0
    lighting: str = "full"
    seed: int = 0
    width: int = 640
    height: int = 480
    colours: list[tuple[int, int, int]] | None = None
    markers: bool = False
    stagger_s: float = 0.3
    dvs: DvsParams | None = None
    arena_m: float = 1.83
    body: str = "3d"
    shadow: bool = True
    camera_height_m: float = 2.5
    nadir_offset_m: tuple[float, float] = NADIR_OFFSET_M
    spin_dps: float | None = 150.0

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ValueError naming the field and its allowed values when a field has the wrong
        type (a string, NaN, an infinity, ...) or is out of range. Run on construction (and by
        :func:`generate`, for fields changed since)."""
        own = "Scenario"
        check_number(own, "n_robots", self.n_robots, 0, 50, integer=True)
        check_choice(own, "pattern", self.pattern, PATTERNS)
        check_number(own, "power", self.power, 0.05, 1.0, unit="(a fraction of full power)")
        check_number(own, "duration_s", self.duration_s, 0, lo_open=True, unit="s")
        check_choice(own, "lighting", self.lighting, LIGHTING_LEVELS)
        check_number(own, "seed", self.seed, 0, integer=True)
        check_number(own, "width", self.width, 16, 4096, integer=True, unit="px")
        check_number(own, "height", self.height, 16, 4096, integer=True, unit="px")
        check_bool(own, "markers", self.markers)
        check_number(own, "stagger_s", self.stagger_s, 0, unit="s")
        if self.dvs is not None and not isinstance(self.dvs, DvsParams):
            raise ValueError(f"Scenario.dvs must be a DvsParams or None (the defaults), got {self.dvs!r}")
        check_number(own, "arena_m", self.arena_m, 0.1, 100.0, unit="m")
        check_choice(own, "body", self.body, BODIES)
        check_bool(own, "shadow", self.shadow)
        check_number(own, "camera_height_m", self.camera_height_m, 0.5, 10.0, unit="m")
        off = self.nadir_offset_m
        if (isinstance(off, (str, bytes)) or not hasattr(off, "__len__") or len(off) != 2
                or not all(_is_real(c) and math.isfinite(float(c)) and abs(float(c)) <= self.arena_m for c in off)):
            raise ValueError(f"Scenario.nadir_offset_m must be (dx, dy), finite m within the arena side "
                             f"({self.arena_m:g} m) of the arena centre, got {self.nadir_offset_m!r}")
        check_number(own, "spin_dps", self.spin_dps, 0, 1000, lo_open=True, unit="deg/s",
                     none="no tread scrubbing: ideal skid kinematics")
        if self.colours is not None:
            if isinstance(self.colours, (str, bytes)) or not hasattr(self.colours, "__len__"):
                raise ValueError(f"Scenario.colours must be a list of (r, g, b) or None, got {self.colours!r}")
            if len(self.colours) < self.n_robots:
                raise ValueError(f"Scenario.colours: {len(self.colours)} colours for {self.n_robots} robots")
            for i, c in enumerate(self.colours):
                if (isinstance(c, (str, bytes)) or not hasattr(c, "__len__") or len(c) != 3
                        or not all(_is_int(v) and 0 <= v <= 255 for v in c)):
                    raise ValueError(f"Scenario.colours[{i}] must be (r, g, b), integers 0..255, got {c!r}")

    def camera(self) -> CeilingCamera:
        """The ceiling event camera of this scenario (geometry, body model, shadow)."""
        return CeilingCamera(self.width, self.height, self.arena_m, seed=self.seed,
                             camera_height_m=self.camera_height_m,
                             nadir_offset_m=tuple(self.nadir_offset_m), body=self.body,
                             shadow=self.shadow)

    def robot_specs(self) -> list[RobotSpec]:
        """The robots of this scenario, placed at the start of their routes."""
        plans = make_plans(self.pattern, self.n_robots, self.arena_m, self.duration_s,
                           self.stagger_s)
        specs = []
        for i, plan in enumerate(plans):
            name, rgb = COLOURS[i % len(COLOURS)]
            if self.colours is not None:
                rgb, name = tuple(self.colours[i]), f"robot{i}"
            specs.append(RobotSpec(name=f"{name}{i}" if self.colours is None else name,
                                   color_rgb=rgb, marker_id=i if self.markers and i < 50 else None,
                                   start=plan.start_pose(), spin_dps_full=self.spin_dps))
        return specs


@dataclass
class Recording:
    """A simulated recording.

    Attributes:
        events: :data:`arena.events.EVENT_DTYPE` array sorted by ``t`` (sensor frame, µs).
        is_signal: bool per event, True when caused by a robot (False: noise, hot pixels).
        truth: :data:`simulator.simulation.TRUTH_DTYPE` rows (t_us, robot index, x_m, y_m,
            yaw_rad, vx_mps, vy_mps; arena frame) every 2 ms for every robot.
        robot_names: name of robot index i.
        calibration: ``{"image_size": [w, h], "points": [{"pixel": [u, v], "arena_m": [x, y]}]}``.
        width, height: sensor size, px.
        homography: 3 x 3 arena (m) -> sensor (px).
        robots: the robot specs (colours, markers, geometry).
        scenario: what was simulated.
    """

    events: np.ndarray
    is_signal: np.ndarray
    truth: np.ndarray
    robot_names: list[str]
    calibration: dict
    width: int
    height: int
    homography: np.ndarray
    robots: list[RobotSpec] = field(default_factory=list)
    scenario: Scenario | None = None

    def first_motion_us(self, min_speed_mps: float = 0.02) -> dict[str, int | None]:
        """Per robot name, the first truth time (µs) its speed exceeds ``min_speed_mps``
        (None if it never moves): "a robot counts once it has moved"."""
        out: dict[str, int | None] = {}
        speed = np.hypot(self.truth["vx_mps"], self.truth["vy_mps"])
        for i, name in enumerate(self.robot_names):
            m = (self.truth["robot"] == i) & (speed > min_speed_mps)
            out[name] = int(self.truth["t_us"][m][0]) if m.any() else None
        return out

    def truth_of(self, robot: int) -> np.ndarray:
        """Truth rows of robot index ``robot``, in time order."""
        return self.truth[self.truth["robot"] == robot]


def generate(scenario: Scenario, progress=None) -> Recording:
    """Simulate ``scenario`` as fast as possible and return the :class:`Recording`.

    ``progress``, if given, is called with the simulated time (s) every 0.1 s.
    """
    scenario.validate()
    specs = scenario.robot_specs()
    world = World(specs, arena_m=scenario.arena_m, lighting=scenario.lighting, seed=scenario.seed)
    camera = scenario.camera()
    plans = make_plans(scenario.pattern, scenario.n_robots, scenario.arena_m,
                       scenario.duration_s, scenario.stagger_s)
    pilot = Autopilot(world, plans, scenario.power) if scenario.pattern != "still" else None
    sim = Simulation(world, camera, scenario.dvs, pilot, seed=scenario.seed + 1)
    total = int(round(scenario.duration_s * 1e6 / sim.step_us))
    block = max(1, 100_000 // sim.step_us)   # 0.1 s of steps per sensor call
    evs, sigs, truths = [], [], []
    done = 0
    while done < total:
        k = min(block, total - done)
        ev, sig, tr = sim.run(k)
        evs.append(ev)
        sigs.append(sig)
        truths.append(tr)
        done += k
        if progress is not None:
            progress(done * sim.step_us * 1e-6)
    return Recording(
        events=np.concatenate(evs), is_signal=np.concatenate(sigs),
        truth=np.concatenate(truths) if truths else np.zeros(0, TRUTH_DTYPE),
        robot_names=[s.name for s in specs], calibration=camera.calibration(),
        width=camera.width, height=camera.height, homography=camera.H.copy(),
        robots=specs, scenario=scenario)
