"""Contracts defined in one place: one homography fitter and one CalibrationError
(arena.homography), one Zenoh settings model and one list of modes (arena.config), one set of
track-state names (arena.messages), one definition of the tracks and truth CSV headers and dtypes
(arena.formats.tables)."""

from __future__ import annotations

import ast
import dataclasses
import functools
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("arena", "camera_edge", "tracker", "robot_bridge", "groundtruth", "simulator", "viewer", "recorder",
            "demo", "ros2", "bench")
#: the simulator builds its true camera from four exact corners: the world it stands in for, not a
#: calibration (and it stays independent of the code it tests)
SIMULATOR_GEOMETRY = {"simulator/camera.py", "simulator/webcam.py"}


@functools.cache
def _parsed() -> tuple:
    return tuple((path.relative_to(ROOT).as_posix(), ast.parse(path.read_text(encoding="utf-8"), path.relative_to(ROOT).as_posix()))
                 for pkg in PACKAGES for path in sorted((ROOT / pkg).rglob("*.py")))


def _modules():
    """(path relative to the checkout, parsed module) of every module of the code (not the tests)."""
    return iter(_parsed())


def _calls(tree: ast.AST, name: str) -> bool:
    return any(isinstance(n, ast.Attribute) and n.attr == name for n in ast.walk(tree))


def _classes(tree: ast.AST) -> set[str]:
    return {n.name for n in ast.walk(tree) if isinstance(n, ast.ClassDef)}


def test_one_homography_fitter_and_one_calibration_error():
    fitters, perspective, errors = [], [], []
    for rel, tree in _modules():
        if _calls(tree, "findHomography"):
            fitters.append(rel)
        if _calls(tree, "getPerspectiveTransform") and rel not in SIMULATOR_GEOMETRY:
            perspective.append(rel)
        if "CalibrationError" in _classes(tree):
            errors.append(rel)
    assert fitters == ["arena/homography.py"], "fit homographies with arena.homography.fit_homography"
    assert perspective == [], "fit homographies with arena.homography.fit_homography"
    assert errors == ["arena/homography.py"], "raise arena.homography.CalibrationError"


def test_the_services_calibration_errors_are_the_one_class():
    from arena.homography import CalibrationError
    from groundtruth.homography import CalibrationError as gt_error
    from tracker.calibration import CalibrationError as tracker_error

    assert gt_error is CalibrationError and tracker_error is CalibrationError


def test_one_zenoh_settings_model():
    from arena import config, session

    zenoh_classes = [(rel, c) for rel, tree in _modules() for c in _classes(tree) if c.startswith("Zenoh")]
    assert zenoh_classes == [("arena/config.py", "ZenohSettings")]
    assert session.ZenohSettings is config.ZenohSettings and session.MODES is config.MODES
    assert isinstance(config.LabConfig().zenoh, config.ZenohSettings)
    fields = {f.name for f in dataclasses.fields(config.ZenohSettings)}
    assert fields == {"mode", "connect", "listen", "multicast_scouting", "lease_ms", "config_file", "tls", "user",
                      "password", "cfg"}


def test_the_lab_zenoh_table_resolves_as_before(tmp_path):
    """The lab's [zenoh] table is a ZenohSettings: without connect a client still goes to the
    default router and a router connects to nothing; resolving does not change the lab's copy."""
    from arena.config import DEFAULT_ROUTER, parse_lab_config
    from arena.session import resolve_settings, to_zenoh_config

    lab = parse_lab_config({"zenoh": {"mode": "peer", "listen": ["tcp/0.0.0.0:7448"], "lease_ms": 500}})
    s = resolve_settings(None, lab)
    assert (s.mode, s.connect, s.listen, s.lease_ms) == ("peer", [DEFAULT_ROUTER], ["tcp/0.0.0.0:7448"], 500)
    s.listen.append("tcp/127.0.0.1:1")
    assert lab.zenoh.listen == ["tcp/0.0.0.0:7448"]
    assert resolve_settings(None, parse_lab_config({"zenoh": {"mode": "router"}})).connect == []
    assert resolve_settings(None, parse_lab_config({})).connect == [DEFAULT_ROUTER]
    conf = to_zenoh_config(s)
    assert conf.get_json("mode") == '"peer"' and s.to_zenoh_config().get_json("listen/endpoints") == \
        '["tcp/0.0.0.0:7448","tcp/127.0.0.1:1"]'


def test_one_set_of_track_states():
    from arena.messages import COASTING, CONFIRMED, TENTATIVE, TRACK_STATES, Track

    assert TRACK_STATES == (TENTATIVE, CONFIRMED, COASTING) == ("tentative", "confirmed", "coasting")
    assert Track.__dataclass_fields__["state"].metadata["choices"] is TRACK_STATES


#: columns that make a sequence of strings (or of dtype fields) a tracks / truth CSV header
TRACK_KEY = {"t_us", "track_id", "x_m", "y_m"}
TRUTH_KEY = {"t_us", "robot", "x_m", "y_m"}
#: copies that must stay (module, kind, name assigned): the simulator's own truth array (robot = an
#: index into its robot list, which the truth CSV writer names) and the required columns of ros2.bag's
#: stdlib-only reader (``arena export`` imports no numpy, so not arena.formats); each must equal the
#: contract's columns
COPIES = {("simulator/simulation.py", "truth", "TRUTH_DTYPE"): "TRUTH_CSV_HEADER",
          ("ros2/bag.py", "tracks", ""): "TRACK_REQUIRED", ("ros2/bag.py", "truth", ""): "TRUTH_REQUIRED"}


def _header_definitions(rel: str, tree: ast.AST) -> list[tuple[str, str, int, tuple]]:
    """(kind, name assigned or "", line, columns) of every tracks or truth header the module spells out:
    a tuple/list of column names or of dtype fields with the key columns, or a string that starts
    with ``t_us,`` (docstrings, help and error texts that mention the columns are not definitions)."""
    docs = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)}
    names = {}   # id(value node) -> the name it is assigned to
    for n in ast.walk(tree):
        if isinstance(n, (ast.Assign, ast.AnnAssign)) and n.value is not None:
            target = n.targets[0] if isinstance(n, ast.Assign) else n.target
            label = target.id if isinstance(target, ast.Name) else getattr(target, "attr", "")
            for sub in ast.walk(n.value):
                names.setdefault(id(sub), label)
    found = []
    for n in ast.walk(tree):
        if isinstance(n, (ast.Tuple, ast.List)):
            cols = []
            for e in n.elts:
                if isinstance(e, ast.Tuple) and e.elts:   # a dtype field ("name", "<f8")
                    e = e.elts[0]
                if isinstance(e, ast.Constant) and isinstance(e.value, str):
                    cols.append(e.value)
            kind = "tracks" if TRACK_KEY <= set(cols) else "truth" if TRUTH_KEY <= set(cols) else None
        elif isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs \
                and n.value.startswith("t_us,"):
            cols = n.value.strip().split(",")
            kind = "tracks" if "track_id" in cols else "truth"
        else:
            continue
        if kind:
            found.append((kind, names.get(id(n), ""), n.lineno, tuple(cols)))
    return found


def test_one_definition_of_the_tracks_and_truth_csv_headers():
    """The tracks CSV and the truth CSVs are spelled out only in arena.formats.tables: a module that
    writes or reads them takes the header, dtype or required columns from there."""
    from arena.formats import tables

    found = [(rel, kind, name, cols) for rel, tree in _modules() for kind, name, _, cols in _header_definitions(rel, tree)]
    where = {(rel, kind, name) for rel, kind, name, _ in found}
    others = sorted(w for w in where if w[0] != "arena/formats/tables.py" and w not in COPIES)
    assert others == [], f"a second tracks/truth CSV header or dtype: {others}; use arena.formats.tables"
    for rel, kind, name, cols in found:
        if (rel, kind, name) in COPIES:
            assert cols == getattr(tables, COPIES[rel, kind, name]), (rel, name, cols)
    where = {w for w in where if w not in COPIES}
    assert {(k, n) for r, k, n in where} == {
        ("tracks", "TRACK_CSV_HEADER"), ("tracks", "TRACK_REQUIRED"), ("tracks", "TRACK_DTYPE"),
        ("truth", "TRUTH_CSV_HEADER"), ("truth", "GROUNDTRUTH_CSV_HEADER"), ("truth", "TRUTH_REQUIRED"),
        ("truth", "TRUTH_DTYPE")}
    assert tables.TRACK_DTYPE.names == tables.TRACK_CSV_HEADER[:-1]      # all but host_ns
    assert tables.TRUTH_DTYPE.names == tables.TRUTH_CSV_HEADER
    for header in (tables.TRUTH_CSV_HEADER, tables.GROUNDTRUTH_CSV_HEADER):
        assert header[:len(tables.TRUTH_REQUIRED)] == tables.TRUTH_REQUIRED


def test_the_header_scan_finds_a_second_definition():
    """The scan above can fail: a copied header, dtype or header string is found, not a docstring."""
    tree = ast.parse('''"""t_us,track_id,x_m,y_m in a docstring"""
COLUMNS = ("t_us", "track_id", "robot", "x_m", "y_m")
GT = np.dtype([("t_us", "<i8"), ("robot", "U64"), ("x_m", "<f8"), ("y_m", "<f8")])
class W:
    HEADER = "t_us,robot,x_m,y_m,yaw_rad\\n"
def f(rows):
    return read(rows, ("t_us", "robot", "x_m", "y_m"), help="columns t_us,robot,x_m,y_m")
''')
    assert [d[:3] for d in _header_definitions("x.py", tree)] == [
        ("tracks", "COLUMNS", 2), ("truth", "GT", 3), ("truth", "HEADER", 5), ("truth", "", 7)]
    assert _header_definitions("x.py", tree)[2][3] == ("t_us", "robot", "x_m", "y_m", "yaw_rad")


def test_the_services_share_the_one_csv_writers_and_readers():
    """The names the services (and their CLIs) still import from their own modules are the
    arena.formats.tables objects, not copies."""
    from arena.formats import tables
    from groundtruth import metrics
    from simulator import recording
    from tracker import pipeline

    # no second name for them elsewhere: their users import arena.formats.tables
    assert not hasattr(pipeline, "TrackCsvWriter") and not hasattr(pipeline, "TRACK_CSV_HEADER")
    assert not hasattr(recording, "TruthCsvWriter") and not hasattr(metrics, "TRACK_DTYPE")
    assert not hasattr(metrics, "TRUTH_DTYPE")
    for gone in ("read_tracks_csv", "read_truth_csv", "write_tracks_csv", "write_truth_csv", "CsvFormatError",
                 "TRACK_COLUMNS", "TRACK_REQUIRED", "TRUTH_REQUIRED"):
        assert not hasattr(metrics, gone), gone
