"""Robot bridge: drive Zumo-class robots over Bluetooth/USB/simulator serial links.

Modules (pure unless noted; the wire protocol, COBS + CRC-16 frames shared with the firmware and
the simulator's robot emulator, is ``arena.robot_protocol``, spec in ``docs/robot-protocol.md``):

* ``firmware/`` — reference Zumo 32U4 Arduino sketch with the same framing in C.
* ``link`` (I/O) — one robot's serial link by pyserial URL, reconnect, RTT, link quality.
* ``missions`` — circle, square, figure8, back_and_forth, waypoints, stop-and-go.
* ``odometry`` — encoder dead reckoning and its calibration.
* ``control`` — wheel PID, paper mode and closed loop (pure pursuit on fused track +
  odometry pose), path error.
* ``logs`` (I/O) — per-mission CSV + JSON manifest, flushed, rotated, gaps explicit.
* ``core`` (I/O, no Zenoh) — one robot's domain core: link, mission state, stop/e-stop, geofence,
  battery, clocks, logs.
* ``service`` (I/O) — the bridge on Zenoh: publishers and queryables wired to the core.
* ``cli`` — ``arena bridge run|mission|stop|estop|clear|led`` (``python -m robot_bridge``).
"""
