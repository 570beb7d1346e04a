"""`arena view` takes host, port, accumulate_ms and rate from the lab file's [services.viewer];
flags win; a wrong value is a clear error naming the file, the table and the key."""

from __future__ import annotations

import os
import re
import subprocess
import urllib.request

from arena.cli import main
from tests.conftest import arena_cmd, free_port, wait_for_line


def _serve(router, *args: str) -> str:
    """Start `arena view ARGS`, return the URL it serves on (then stop it)."""
    view = subprocess.Popen(arena_cmd("view", *args, *router.args), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = wait_for_line(view, "viewer on", timeout=60)
        url = re.search(r"http://\S+/", line).group(0)
        with urllib.request.urlopen(url + "state.json", timeout=10) as r:   # it really serves there
            assert r.status == 200
        return url
    finally:
        view.terminate()
        view.communicate(timeout=15)


def test_viewer_serves_on_the_lab_port_and_a_flag_wins(router, tmp_path):
    port = free_port()
    lab = tmp_path / "lab.toml"
    lab.write_text(f'[zenoh]\nconnect = ["{router.endpoint}"]\n[services.viewer]\nport = {port}\nrate = 5\n')
    assert _serve(router, "--lab", str(lab)) == f"http://127.0.0.1:{port}/"
    other = free_port()
    assert _serve(router, "--lab", str(lab), "--port", str(other)) == f"http://127.0.0.1:{other}/"


def test_viewer_lab_option_mistakes_are_clear(tmp_path, capsys):
    lab = tmp_path / "lab.toml"
    for text, needle in [("port = 'web'\n", "services.viewer.port: expected an integer in [0, 65535], got 'web'"),
                         ("accumulate_ms = 0\n", "services.viewer.accumulate_ms: expected a finite number > 0, got 0"),
                         ("colour = 'red'\n", "services.viewer: unknown key(s) colour; known: host, port")]:
        lab.write_text("[services.viewer]\n" + text)
        assert main(["view", "--lab", str(lab)]) == 2
        err = capsys.readouterr().err
        assert f"arena view: {lab}: {needle}" in err, err
