"""``arena calibrate --nadir X,Y`` with a negative X (a lens outside the mat): argparse read
``-0.2,0.9`` as an unknown option and failed with "expected one argument"."""

from __future__ import annotations

import json

import pytest

from arena.cli import main

PTS = ["112,431:0,0", "528,431:1.83,0", "528,15:1.83,1.83", "112,15:0,1.83"]


@pytest.mark.parametrize("nadir,expected", [("-0.2,0.9", [-0.2, 0.9]), ("-.5,-1", [-0.5, -1.0]),
                                            ("0.9,-1", [0.9, -1.0])])
def test_a_negative_nadir_is_a_value(tmp_path, nadir, expected):
    out = tmp_path / "c.json"
    assert main(["calibrate", "--size", "640x480", "--points", *PTS, "--nadir", nadir, "-o", str(out)]) == 0
    assert json.loads(out.read_text())["nadir_m"] == expected


def test_a_nadir_far_outside_is_refused_by_its_check_not_by_argparse(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", "--size", "640x480", "--points", *PTS, "--nadir", "-50,1", "-o", str(tmp_path / "c.json")])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "expected one argument" not in err
    assert "(-50.000, 1.000) m is 50.00 m from the arena" in err
    with pytest.raises(SystemExit):   # a negative value still does not swallow an option name
        main(["calibrate", "--size", "640x480", "--points", *PTS, "--nadir", "-o", str(tmp_path / "c.json")])
    assert "argument --nadir: expected one argument" in capsys.readouterr().err
