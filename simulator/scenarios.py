"""Built-in scenarios: N robots driving the paper's patterns, recorded with exact truth.

>>> rec = generate(Scenario(n_robots=2, pattern="circle", power=0.5, duration_s=2.0))
>>> rec.events["t"][:3], rec.truth[:2], rec.first_motion_us()

A :class:`Recording` carries the events (sensor frame, µs), a signal/noise label per
event, the truth poses (arena frame, >= 200 Hz), the robot names and the camera
calibration, so a tracker can be run and scored offline.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from simulator.autopilot import PATTERNS, Autopilot, make_plans
from simulator.camera import BODIES, NADIR_OFFSET_M, CeilingCamera
from simulator.dvs import DvsParams
from simulator.simulation import TRUTH_DTYPE, Simulation
from simulator.world import LIGHTING_LEVELS, RobotSpec, World

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

    def validate(self) -> None:
        """Raise ValueError with a clear message when a field is out of range."""
        if not 0 <= self.n_robots <= 50:
            raise ValueError(f"n_robots must be in 0..50, got {self.n_robots}")
        if self.pattern not in PATTERNS:
            raise ValueError(f"pattern must be one of {PATTERNS}, got {self.pattern!r}")
        if not 0.05 <= self.power <= 1.0:
            raise ValueError(f"power must be a fraction in [0.05, 1], got {self.power}")
        if self.duration_s <= 0:
            raise ValueError(f"duration_s must be > 0, got {self.duration_s}")
        if self.lighting not in LIGHTING_LEVELS:
            raise ValueError(f"lighting must be one of {LIGHTING_LEVELS}, got {self.lighting!r}")
        if self.body not in BODIES:
            raise ValueError(f"body must be one of {BODIES}, got {self.body!r}")
        if not 0.5 <= self.camera_height_m <= 10.0:
            raise ValueError(f"camera_height_m must be in 0.5..10 m, got {self.camera_height_m}")
        off = np.asarray(self.nadir_offset_m, dtype=float)
        if off.shape != (2,) or not np.all(np.isfinite(off)) or np.any(np.abs(off) > self.arena_m):
            raise ValueError(f"nadir_offset_m must be (dx, dy) within the arena side, got {self.nadir_offset_m!r}")
        if self.colours is not None and len(self.colours) < self.n_robots:
            raise ValueError(f"{len(self.colours)} colours for {self.n_robots} robots")

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
