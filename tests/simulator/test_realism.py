"""Realism of the simulated event camera (issue 19): plain robots, 3-D bodies seen through a
pinhole camera with an off-centre nadir, contact shadow, vignetting, leak and shot noise,
refractory period. Small sensors and short scripted paths (no autopilot)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simulator.camera import CeilingCamera, apply_homography
from simulator.dvs import NOISE_RATE_HZ, DvsParams, DvsSensor
from simulator.scenarios import Scenario
from simulator.world import RobotSpec

QUIET = dict(noise_rate_hz=0.0, hot_pixels=0, leak_rate_hz=0.0)


def drive(cam, robot, path, seconds, params=None, lighting="full"):
    s = DvsSensor(cam, [robot], lighting=lighting, params=params or DvsParams(**QUIET), seed=0)
    s.reset(np.array([path(0.0)]), 0)
    n = int(round(seconds * 1000))
    times = np.arange(1, n + 1, dtype=np.int64) * 1000
    poses = np.array([[path(t * 1e-6)] for t in times])
    evs, sigs = [], []
    for a in range(0, n, 100):
        e, g = s.advance(poses[a:a + 100], times[a:a + 100])
        evs.append(e)
        sigs.append(g)
    return np.concatenate(evs), np.concatenate(sigs), s


def render(cam, robot, pose):
    """Reflectance image of the scene with ``robot`` at ``pose`` (the settled log level)."""
    s = DvsSensor(cam, [robot], params=DvsParams(**QUIET, vignetting=0, lamp_falloff=0))
    s.reset(np.array([pose]), 0)
    return np.exp(s._llp.astype(float)) - s.params.dark_current


@pytest.fixture(scope="module")
def cam():
    return CeilingCamera(320, 240)


def test_plain_dark_shell_leading_off_bar_trailing_on_bar_nothing_between(cam):
    spec = Scenario(n_robots=1, colours=[(25, 25, 25)]).robot_specs()[0]     # the default robot
    assert spec.marker_id is None
    x0, y0, v = 0.6, 0.9, 0.3
    ev, sig, _ = drive(cam, spec, lambda t: (x0 + v * t, y0, 0.0), 0.4)
    ev = ev[sig & (ev["t"] > 100_000)]
    t = ev["t"] * 1e-6
    # along-track distance of each event from the robot centre, m (events mapped to the mats)
    xy = apply_homography(cam.H_inv, np.column_stack([ev["x"], ev["y"]]).astype(float))
    s = xy[:, 0] - (x0 + v * t)
    lead, trail = ev[s > 0.03], ev[s < -0.03]
    between = np.abs(s) < 0.025
    assert len(lead) > 300 and len(trail) > 300
    assert (lead["p"] == 0).mean() > 0.85, "leading edge of a dark shell on white mats: OFF"
    assert (trail["p"] == 1).mean() > 0.85, "trailing edge: ON"
    assert between.mean() < 0.10, f"{between.mean():.2f} of the events inside a plain shell"
    # a marker print fills the interior with events
    marked = RobotSpec("m", (25, 25, 25), marker_id=3)
    ev_m, sig_m, _ = drive(cam, marked, lambda t: (x0 + v * t, y0, 0.0), 0.4)
    ev_m = ev_m[sig_m & (ev_m["t"] > 100_000)]
    xy_m = apply_homography(cam.H_inv, np.column_stack([ev_m["x"], ev_m["y"]]).astype(float))
    s_m = xy_m[:, 0] - (x0 + v * ev_m["t"] * 1e-6)
    assert (np.abs(s_m) < 0.025).mean() > 2 * between.mean()


def test_defaults_are_a_real_lab():
    sc = Scenario()
    assert sc.markers is False and sc.body == "3d" and sc.shadow is True
    assert sc.camera_height_m == 2.5 and np.hypot(*sc.nadir_offset_m) > 0.05
    p = DvsParams()
    assert p.threshold_on == p.threshold_off == 0.25 and p.threshold_sigma == 0.03
    assert p.refractory_us == 500 and p.leak_rate_hz > 0 and p.shot_noise
    assert NOISE_RATE_HZ == {"full": 0.5, "dimmed": 1.0, "dark": 2.0}


@pytest.mark.parametrize("h,offset", [(1.8, (0.3, -0.2)), (3.0, (0.0, 0.0))])
def test_height_and_nadir_move_a_corner_robot_by_the_pinhole_amount(h, offset):
    """A flat plate 4 cm up near a corner: its event cloud, mapped to the mats with the
    floor homography, is centred where the pinhole puts it, nadir + (p - nadir) H/(H - z)."""
    cam = CeilingCamera(320, 240, camera_height_m=h, nadir_offset_m=offset, body="flat",
                        shadow=False)
    x0, y0 = 0.25, 0.3
    path = lambda t: (x0 + 0.1 * math.sin(6 * t), y0 + 0.1 * math.cos(6 * t), 6 * t)
    ev, sig, _ = drive(cam, RobotSpec("r", (25, 25, 25)), path, 0.5)
    ev = ev[sig & (ev["t"] > 50_000)]
    t = ev["t"] * 1e-6
    centre = np.column_stack([x0 + 0.1 * np.sin(6 * t), y0 + 0.1 * np.cos(6 * t)])
    seen = apply_homography(cam.H_inv, np.column_stack([ev["x"], ev["y"]]).astype(float))
    nadir = np.array([0.915 + offset[0], 0.915 + offset[1]])
    want = nadir + (centre - nadir) * h / (h - 0.04)
    shift = np.linalg.norm((want - centre).mean(0))
    err = np.linalg.norm((seen - want).mean(0))
    assert shift > 0.008                       # the parallax is large enough to be seen
    # (the photoreceptor lag of the dark shell biases the cloud a little along the motion)
    assert err < 0.35 * shift, f"cloud {err * 1000:.1f} mm off the pinhole prediction"
    cal = cam.calibration()
    assert cal["camera_height_m"] == h and cal["nadir_m"] == pytest.approx(nadir.tolist(), abs=1e-4)
    assert cal["nadir_px"] == pytest.approx(cam.to_pixels(nadir[None])[0].tolist(), abs=1e-2)


def test_3d_body_shows_the_wall_facing_the_lens_and_hides_the_far_one():
    """Ray-traced body: at a corner far from the nadir, the shell wall that faces the lens is
    seen (darker wall shading between the top and the foot), and the top is pushed away
    from the nadir; the projection matrix maps the top corner where it appears."""
    cam = CeilingCamera(640, 480, nadir_offset_m=(0.0, 0.0), shadow=False)
    robot = RobotSpec("r", (225, 225, 220))
    img = render(cam, robot, (0.3, 0.3, 0.0))
    flat = render(CeilingCamera(640, 480, nadir_offset_m=(0.0, 0.0), shadow=False, body="flat"),
                  robot, (0.3, 0.3, 0.0))
    assert not np.allclose(img, flat, atol=0.02)
    # walk from the robot centre towards the nadir (+x, +y): shell top, then its wall, then mat
    top_refl = 0.04 + 0.90 * 0.75
    u, v = cam.project([[0.3, 0.3, 0.04]])[0]
    du, dv = cam.project([[0.31, 0.31, 0.04]])[0] - (u, v)
    line = [img[int(round(v + k * dv / np.hypot(du, dv))), int(round(u + k * du / np.hypot(du, dv)))]
            for k in range(0, 20)]
    assert min(line) < 0.7 * top_refl          # the wall (half light) or treads are seen


def test_contact_shadow_darkens_the_mat_around_the_robot_and_switches_off():
    robot = RobotSpec("r", (225, 225, 220))
    on = render(CeilingCamera(640, 480, shadow=True), robot, (0.9, 0.9, 0.0))
    off = render(CeilingCamera(640, 480, shadow=False), robot, (0.9, 0.9, 0.0))
    cam = CeilingCamera(640, 480)
    u, v = cam.to_pixels([[0.9, 0.9 + 0.05 + 0.005]])[0]     # 5 mm beside the left side
    u, v = int(round(u)), int(round(v))
    assert on[v, u] < 0.92 * off[v, u]
    far = cam.to_pixels([[0.9, 0.9 + 0.1]])[0].round().astype(int)
    assert on[far[1], far[0]] == pytest.approx(off[far[1], far[0]], rel=1e-4)


def test_vignetting_dims_the_corners_and_lowers_their_contrast_in_dim_light():
    cam = CeilingCamera(320, 240)
    on = DvsSensor(cam, [], params=DvsParams()).gain
    off = DvsSensor(cam, [], params=DvsParams(vignetting=0, lamp_falloff=0)).gain
    centre = cam.to_pixels([[0.915, 0.915]])[0].round().astype(int)
    corners = cam.to_pixels([[0.05, 0.05], [1.78, 0.05], [1.78, 1.78], [0.05, 1.78]]).round().astype(int)
    g = np.array([on[v, u] for u, v in corners])
    assert on[centre[1], centre[0]] > 0.97
    assert np.all((0.6 < g) & (g < 0.82)), g           # 20-40 % darker at the mat corners
    assert np.all(off == 1.0)
    # a dark robot in a corner under dark lighting: less contrast, fewer events
    path = lambda t: (0.15 + 0.3 * t, 0.2, 0.0)
    black = RobotSpec("r", (25, 25, 25))
    n_on = drive(cam, black, path, 0.4, DvsParams(**QUIET), "dark")[1].sum()
    n_off = drive(cam, black, path, 0.4, DvsParams(**QUIET, vignetting=0, lamp_falloff=0), "dark")[1].sum()
    assert 0 < n_on < 0.97 * n_off


@pytest.mark.parametrize("rate", [0.1, 2.0])
def test_background_rate_is_as_configured_and_more_in_dark_pixels(rate):
    cam = CeilingCamera(320, 240)
    params = DvsParams(noise_rate_hz=rate, hot_pixels=0, leak_rate_hz=0.0)
    s = DvsSensor(cam, [], params=params, seed=3)
    s.reset(np.zeros((0, 3)), 0)
    ev, sig = s.advance(np.zeros((1000, 0, 3)), np.arange(1, 1001) * 1000)
    assert not sig.any()
    assert len(ev) == pytest.approx(rate * cam.width * cam.height, rel=0.1)
    # shot noise: pixels of the dark floor around the mats fire more than the white mats
    count = np.zeros((cam.height, cam.width))
    np.add.at(count, (ev["y"], ev["x"]), 1)
    L = cam.arena_m
    mats = (cam.ax > 0.2) & (cam.ax < L - 0.2) & (cam.ay > 0.2) & (cam.ay < L - 0.2)
    floor = (cam.ax < -0.02) | (cam.ax > L + 0.02) | (cam.ay < -0.02) | (cam.ay > L + 0.02)
    assert count[floor].mean() > 1.3 * count[mats].mean()
    flat = DvsSensor(cam, [], params=DvsParams(noise_rate_hz=rate, hot_pixels=0, leak_rate_hz=0.0,
                                               shot_noise=False), seed=3)
    assert np.allclose(flat._noise_cdf, np.arange(1, cam.width * cam.height + 1) * rate)


def test_leak_events_are_on_and_scale_with_light():
    cam = CeilingCamera(160, 120)
    n = {}
    for lighting in ("full", "dimmed"):
        s = DvsSensor(cam, [], lighting=lighting,
                      params=DvsParams(noise_rate_hz=0.0, hot_pixels=0, leak_rate_hz=1.0), seed=4)
        s.reset(np.zeros((0, 3)), 0)
        ev, _ = s.advance(np.zeros((1000, 0, 3)), np.arange(1, 1001) * 1000)
        assert np.all(ev["p"] == 1)
        n[lighting] = len(ev)
    assert n["full"] == pytest.approx(float(DvsSensor(cam, [], params=DvsParams(leak_rate_hz=1.0)).gain.sum()), rel=0.1)
    assert n["dimmed"] == pytest.approx(0.25 * n["full"], rel=0.25)
    s = DvsSensor(cam, [], params=DvsParams(noise_rate_hz=0.0, hot_pixels=0, leak_rate_hz=0.0))
    s.reset(np.zeros((0, 3)), 0)
    assert len(s.advance(np.zeros((500, 0, 3)), np.arange(1, 501) * 1000)[0]) == 0


def test_default_refractory_period_holds_per_pixel(cam):
    ev, sig, _ = drive(cam, RobotSpec("r", (25, 25, 25)), lambda t: (0.6 + 0.46 * t, 0.9, 0.0),
                       0.3, DvsParams(**QUIET))
    ev = ev[sig]
    key = ev["y"].astype(np.int64) * 10_000 + ev["x"]
    order = np.lexsort((ev["t"], key))
    k, t = key[order], ev["t"][order]
    same = k[1:] == k[:-1]
    assert same.sum() > 100
    assert np.diff(t)[same].min() >= 500


def test_bad_geometry_is_refused():
    with pytest.raises(ValueError, match="body"):
        Scenario(body="sphere").validate()
    with pytest.raises(ValueError, match="camera_height_m"):
        Scenario(camera_height_m=0.1).validate()
    with pytest.raises(ValueError, match="nadir_offset_m"):
        Scenario(nadir_offset_m=(float("nan"), 0.0)).validate()
    with pytest.raises(ValueError, match="vignetting"):
        DvsParams(vignetting=-1).validate()
