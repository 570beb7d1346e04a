"""Detect, head and identify every robot from event windows (``arena track``).

Modules, one concern each (pure algorithms unless said otherwise):

- :mod:`tracker.dbscan` — DBSCAN over unique active pixels: ``dbscan_sklearn`` (reference)
  and ``dbscan_grid`` (exact, numba; same core clusters as scikit-learn).
- :mod:`tracker.accumulate` — ``PixelWindow``: per-pixel statistics of the last t_a of
  slices, updated slice by slice.
- :mod:`tracker.detect` — ``PaperDetector`` (the paper: DBSCAN x3, centroids, ON/OFF heading)
  and ``Detector`` (default: physical parameters, noise-adaptive minPts, split by the
  predictions, pose at the window's end, motion and shape headings).
- :mod:`tracker.idtrack` — ``IDTrack``: the paper's Algorithm 1 (k-d tree).
- :mod:`tracker.fleet` — ``FleetTracker``: Kalman prediction, gating, Hungarian assignment,
  tentative/confirmed/coasting life cycle, fleet-size cap.
- :mod:`tracker.calibration` — ``Calibration``: pixel <-> arena homography, JSON files.
- :mod:`tracker.pipeline` — ``Pipeline``: slices -> window -> detections -> tracks (arena m);
  ``iter_slices`` (the tracks CSV it is written to: :mod:`arena.formats.tables`).
- :mod:`tracker.service` (Zenoh I/O) and :mod:`tracker.cli` (``arena track``, ``arena calibrate``).

Typical use::

    from tracker.calibration import load_calibration
    from tracker.pipeline import Pipeline, iter_slices

    pipe = Pipeline(load_calibration("calib.json"))            # fleet tracker, default detector
    for t_end_us, events in iter_slices(chunks, 10_000):
        for track in pipe.push(events, t_end_us):               # tracker.objects.TrackedRobot
            print(track.track_id, track.x, track.y, track.yaw, track.state)
"""

import arena  # noqa: F401 - first, so that numba has a writable cache directory (arena._numba_cache_fallback)
