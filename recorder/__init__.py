"""Run recorder and replay: every ``arena/**`` message into an MCAP file, and back onto Zenoh.

* :mod:`recorder.mcapio` — the file format: :class:`~recorder.mcapio.RunWriter` and
  :func:`~recorder.mcapio.read_run` (no Zenoh, no clocks).
* :mod:`recorder.schemas` — JSON schemas of the small messages (so Foxglove can show them).
* :mod:`recorder.service` — the Zenoh side: ``record`` and ``replay`` loops.
* :mod:`recorder.cli` — ``arena record`` and ``arena replay``.
"""
