"""Run recorder and replay: every ``arena/**`` message into an MCAP file, and back onto Zenoh.

* :mod:`recorder.mcapio` — the file format: :class:`~recorder.mcapio.RunWriter` and
  :func:`~recorder.mcapio.read_run` (no Zenoh, no clocks).
* :mod:`recorder.schemas` — JSON schemas of the small messages (so Foxglove can show them).
* :mod:`recorder.foxglove_views` — arena messages -> Foxglove's well-known schemas (protobuf;
  pure: no Zenoh, no clocks), written by ``arena record`` beside the arena channels.
* :mod:`recorder.service` — the Zenoh side: ``record`` and ``replay`` loops.
* :mod:`recorder.foxglove_live` — ``arena foxglove``'s Zenoh -> Foxglove WebSocket server
  (needs the optional ``foxglove-sdk``).
* :mod:`recorder.cli` — ``arena record``, ``arena replay`` and ``arena foxglove``.
"""
