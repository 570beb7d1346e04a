"""Live web viewer of the arena: ``arena view``.

* :mod:`viewer.state` — what the page shows, built from arena messages (no Zenoh, no HTTP):
  the accumulated event image, tracks with trails, ground truth, telemetry history, services.
* :mod:`viewer.server` — the HTTP server (stdlib): the page, PNG frames, Server-Sent Events.
* :mod:`viewer.service` — Zenoh subscriptions feeding the state.
* ``viewer/static/`` — the one page (HTML, JS, CSS; no build step, no CDN).
"""
