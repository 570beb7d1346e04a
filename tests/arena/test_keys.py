import pytest

from arena import keys
from arena.keys import InvalidKey


def test_builders_make_the_design_keys():
    assert keys.events_key("cam0") == "arena/events/cam0"
    assert keys.robot_key(7) == "arena/robots/7"
    assert keys.robot_key("zumo1") == "arena/robots/zumo1"
    assert keys.groundtruth_key("zumo1") == "arena/groundtruth/zumo1"
    assert keys.telemetry_key("zumo1") == "arena/telemetry/zumo1"
    assert keys.cmd_key("all", "estop") == "arena/cmd/all/estop"
    assert keys.status_key("tracker", "cam0") == "arena/status/tracker/cam0"
    assert keys.alive_key("edge", "cam0") == "arena/alive/edge/cam0"
    assert keys.sim_truth_key("r1") == "arena/sim/truth/r1"


@pytest.mark.parametrize("bad", ["", "a*b", "a/b", "$x", "a#", "what?", "a b", "x" * 65, "..", "."])
def test_bad_names_are_rejected_with_a_clear_message(bad):
    with pytest.raises(InvalidKey) as exc:
        keys.robot_key(bad)
    assert "robot id" in str(exc.value)


def test_unknown_verb_is_rejected():
    with pytest.raises(InvalidKey, match="unknown command verb"):
        keys.cmd_key("zumo1", "explode")


@pytest.mark.parametrize("key,kind,parts", [
    ("arena/events/cam0", "events", {"camera": "cam0"}),
    ("arena/robots/3", "robots", {"id": "3"}),
    ("arena/cmd/zumo1/mission", "cmd", {"robot": "zumo1", "verb": "mission"}),
    ("arena/status/edge/cam0", "status", {"role": "edge", "name": "cam0"}),
    ("arena/sim/truth/r0", "sim_truth", {"robot": "r0"}),
])
def test_parse_round_trip(key, kind, parts):
    p = keys.parse_key(key)
    assert (p.kind, p.parts) == (kind, parts)


@pytest.mark.parametrize("bad", ["other/robots/1", "arena/robots", "arena/robots/a/b", "arena/nope/x",
                                 "arena/robots/*", "arena/cmd/r/explode"])
def test_parse_rejects_non_keys(bad):
    with pytest.raises(InvalidKey):
        keys.parse_key(bad)


#: modules that split strings at "/" that are not Zenoh keys: a source URL, ROS 2 names and types
NOT_KEYS = {"arena/keys.py", "camera_edge/cli.py", "groundtruth/mocap.py", "ros2/cli.py", "ros2/convert.py"}


def test_no_module_splits_a_zenoh_key_by_hand():
    """Keys are parsed by arena.keys.parse_key (one place knows the key space), not split by hand."""
    import ast
    from pathlib import Path

    repo = Path(__file__).resolve().parents[2]
    found = []
    for pkg in ("arena", "camera_edge", "tracker", "groundtruth", "recorder", "viewer", "ros2", "demo"):
        for path in sorted((repo / pkg).rglob("*.py")):
            rel = path.relative_to(repo).as_posix()
            for n in ast.walk(ast.parse(path.read_text())):
                if (isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr in ("split", "rsplit")
                        and n.args and isinstance(n.args[0], ast.Constant) and n.args[0].value == "/"
                        and rel not in NOT_KEYS):
                    found.append(f"{rel}:{n.lineno}")
    assert found == []
