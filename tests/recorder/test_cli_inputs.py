"""Red-team findings on ``arena record``/``replay``/``watch`` inputs: a key expression Zenoh refuses
is one line naming it (no Rust source path), found before anything is opened, so an existing
recording is not overwritten; a --duration that is not a number of seconds is refused."""

from __future__ import annotations

import threading

import pytest

from arena.cli import main
from arena.session import ZenohSettings, open_session

BAD_KEYS = ["arena//tracks", "", "**/**", "a*b", "arena/$*", "?", "#"]


@pytest.mark.parametrize("key", BAD_KEYS)
def test_a_bad_key_leaves_an_existing_recording_alone(tmp_path, capsys, key):
    keep = tmp_path / "keep.mcap"
    keep.write_bytes(b"a recording worth keeping")
    assert main(["record", str(keep), "--keys", key, "-m", "peer", "--no-foxglove"]) == 2
    err = capsys.readouterr().err.strip()
    assert keep.read_bytes() == b"a recording worth keeping"
    assert err.startswith(f"arena record: --keys {key!r} is not a Zenoh key expression: "), err
    assert ".rs:" not in err and ".cargo" not in err and len(err.splitlines()) == 1, err


def test_replay_and_watch_name_a_bad_key_in_one_line(tmp_path, capsys):
    run = tmp_path / "run.mcap"
    from recorder.mcapio import RunWriter
    with RunWriter(run):
        pass
    assert main(["replay", str(run), "--keys", "arena//x", "-m", "peer"]) == 2
    assert "arena replay: --keys 'arena//x' is not a Zenoh key expression: empty chunks" in capsys.readouterr().err
    assert main(["watch", "a*b", "-m", "peer", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "arena watch: key expression 'a*b' is not a Zenoh key expression" in err and ".rs:" not in err


@pytest.mark.parametrize("value", ["nan", "inf", "-1", "0"])
def test_record_refuses_a_duration_that_is_not_seconds(tmp_path, capsys, value):
    assert main(["record", str(tmp_path / "x.mcap"), f"--duration={value}", "-m", "peer"]) == 2
    assert "--duration must be a number of seconds > 0" in capsys.readouterr().err
    assert not (tmp_path / "x.mcap").exists()


def test_record_refuses_an_output_it_cannot_write_before_connecting(tmp_path, capsys):
    (tmp_path / "adir").mkdir()
    # a client with no router would wait for one: refused before that, naming the path
    assert main(["record", str(tmp_path / "adir"), "-m", "client", "-e", "tcp/127.0.0.1:1"]) == 2
    assert f"cannot write {tmp_path / 'adir'}: a folder" in capsys.readouterr().err


def test_record_the_service_refuses_a_bad_key_before_truncating_the_file(tmp_path):
    import zenoh

    from recorder.service import record
    keep = tmp_path / "keep.mcap"
    keep.write_bytes(b"kept")
    with open_session(ZenohSettings(mode="peer", connect=[], listen=[])) as s:
        with pytest.raises(zenoh.ZError):
            record(s, keep, ["arena/robots/*", "arena//x"], threading.Event(), duration_s=0.1)
    assert keep.read_bytes() == b"kept"
