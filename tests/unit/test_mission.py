"""Mission files: the shipped ones are valid; each kind of bad input is a ConfigError naming the
file and the exact field; the CLI turns it into exit code 2 and one line; random mutations of a
valid mission never raise anything but a ConfigError."""

from __future__ import annotations

import copy
import math
import re
import socket
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from hypothesis import HealthCheck, event, given, note, settings
from hypothesis import strategies as st

from vflpcd.app.cli import main
from vflpcd.base.errors import ConfigError
from vflpcd.config.mission import build_controller, load_mission
from vflpcd.base.paths import config_dir
from vflpcd.app.run import build_platform

ROOT = Path(__file__).resolve().parents[2]
MISSIONS = sorted((config_dir() / "missions").glob("*.toml"))
VEHICLE = config_dir() / "missions" / "vehicle_inproc.toml"
QUAD = config_dir() / "missions" / "quad_inproc.toml"
BASE = tomllib.loads(VEHICLE.read_text())
LOG_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} [A-Z]+ ")


# --------------------------------------------------------------------------- a minimal TOML writer
def _toml_string(s: str) -> str:
    out = []
    for ch in s:
        if ch == '"':
            out.append('\\"')
        elif ch == "\\":
            out.append("\\\\")
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_string(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def to_toml(doc: dict) -> str:
    """TOML text of ``doc``: root values first, then one [table] per root table (deeper tables
    and tables in arrays as inline tables)."""
    lines = [f"{_toml_string(k)} = {_toml_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for k, v in doc.items():
        if isinstance(v, dict):
            lines.append(f"\n[{_toml_string(k)}]")
            lines.extend(f"{_toml_string(kk)} = {_toml_value(vv)}" for kk, vv in v.items())
    return "\n".join(lines) + "\n"


def _same(a, b) -> bool:
    """Equality that treats nan as equal to nan and keeps int/float/bool apart."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


# --------------------------------------------------------------------------- helpers
DELETE = object()


def write_mission(tmp_path: Path, doc: dict | None = None, *, name: str = "mission.toml", **changes) -> Path:
    """Write ``doc`` (default: vehicle_inproc.toml) with ``changes``: dotted keys ("loop.rate_hz")
    set to a value, or deleted when the value is ``DELETE``. The log goes to tmp_path/logs."""
    doc = copy.deepcopy(BASE if doc is None else doc)
    doc.setdefault("log", {})["dir"] = str(tmp_path / "logs")
    for dotted, value in changes.items():
        *parents, key = dotted.split(".")
        node = doc
        for p in parents:
            node = node.setdefault(p, {})
        if value is DELETE:
            node.pop(key, None)
        else:
            node[key] = value
    f = tmp_path / name
    f.write_text(to_toml(doc), encoding="utf-8")
    return f


def check(path: Path):
    """What ``vflpcd check`` does: load, build the controller and the platform."""
    mission = load_mission(path)
    controller = build_controller(mission)
    build_platform(mission)
    return mission, controller


def assert_names(err: ConfigError, file: Path, field: str) -> None:
    assert err.file == str(file)
    assert err.field == field
    assert str(err).startswith(f"{file}: {field}: "), str(err)
    assert "\n" not in str(err)


def test_writer_round_trips_the_shipped_missions():
    for path in MISSIONS:
        doc = tomllib.loads(path.read_text())
        assert _same(tomllib.loads(to_toml(doc)), doc)
    odd = {"a": [1, 2.5, "x", True, [], {}], "b": {"c": {"d": float("nan"), "e": -math.inf}, "": 10**30},
           "s": 'q"\\\n\t\x00\x7f é', "t": {"u": [{"v": 1}]}}
    assert _same(tomllib.loads(to_toml(odd)), odd)


# --------------------------------------------------------------------------- the shipped missions
@pytest.mark.parametrize("path", MISSIONS, ids=[p.stem for p in MISSIONS])
def test_shipped_missions_load_and_build(path):
    mission, controller = check(path)
    assert mission.file == path
    assert mission.vehicle_id and mission.scenario.platform in ("ground", "aerial")
    assert controller.name.startswith(mission.controller)
    assert mission.text == path.read_text()


def test_shipped_missions_are_the_documented_ones():
    assert {p.stem for p in MISSIONS} >= {"vehicle_inproc", "quad_inproc", "bench_loop"}
    v = load_mission(VEHICLE)
    assert (v.vehicle_id, v.platform.kind, v.scenario.name) == ("suv1", "inproc", "carsim_avoidance")
    assert v.loop.rate_hz == 20
    assert v.model_path == config_dir() / "models" / "dynamic_bicycle.npz"
    q = load_mission(QUAD)
    assert (q.vehicle_id, q.scenario.platform, q.failsafe.hold) == ("quad1", "aerial", 5.0)
    # defaults of the tables quad_inproc.toml leaves out
    assert (q.workers.executor, q.workers.replan_period, q.workers.refit_period) == ("process", 0.0, 1.0)
    assert (q.loop.sched_fifo, q.loop.priority, q.loop.manual_gc) == (False, 10, True)
    assert (q.failsafe.overrun_streak, q.failsafe.stall, q.failsafe.connect_timeout) == (5, 0.5, 30.0)


def test_route_and_model_resolve_mission_relative_first(tmp_path):
    scen = (config_dir() / "scenarios" / "dense_static.toml").read_text()
    (tmp_path / "myroad.toml").write_text(scen.replace('name = "dense_static"', 'name = "myroad"'))
    (tmp_path / "dynamic_bicycle.npz").write_bytes((config_dir() / "models" / "dynamic_bicycle.npz").read_bytes())
    f = write_mission(tmp_path, **{"route.scenario": "myroad.toml"})
    m = load_mission(f)
    assert m.scenario.name == "myroad"
    assert m.model_path == tmp_path / "dynamic_bicycle.npz"
    # a bare name (no suffix) is looked up in config/scenarios as NAME.toml
    m = load_mission(write_mission(tmp_path, **{"route.scenario": "racing_track"}))
    assert m.scenario.file == config_dir() / "scenarios" / "racing_track.toml"


# --------------------------------------------------------------------------- one malformed field each
LOAD_CASES = {
    # id: (changes, field)
    "vehicle_id missing": ({"vehicle_id": DELETE}, "vehicle_id"),
    "vehicle_id with /": ({"vehicle_id": "suv/1"}, "vehicle_id"),
    "vehicle_id with *": ({"vehicle_id": "suv*"}, "vehicle_id"),
    "vehicle_id empty": ({"vehicle_id": ""}, "vehicle_id"),
    "vehicle_id a number": ({"vehicle_id": 7}, "vehicle_id"),
    "platform.kind unknown": ({"platform.kind": "rover"}, "platform.kind"),
    "platform.kind missing": ({"platform.kind": DELETE}, "platform.kind"),
    "platform mavlink on a ground route": ({"platform.kind": "mavlink"}, "platform.kind"),
    "platform table missing": ({"platform": DELETE}, "platform"),
    "unknown key at top level": ({"vehicle": "suv1"}, "vehicle"),
    "unknown key in route": ({"route.name": "x"}, "route.name"),
    "unknown key in controller": ({"controller.modle": "x.npz"}, "controller.modle"),
    "unknown key in loop": ({"loop.rat_hz": 20}, "loop.rat_hz"),
    "unknown key in workers": ({"workers.executer": "thread"}, "workers.executer"),
    "unknown key in telemetry": ({"telemetry.rate": 10.0}, "telemetry.rate"),
    "unknown key in failsafe": ({"failsafe.stal": 0.5}, "failsafe.stal"),
    "unknown key in log": ({"log.directory": "logs"}, "log.directory"),
    "loop.rate_hz 0": ({"loop.rate_hz": 0}, "loop.rate_hz"),
    "loop.rate_hz -5": ({"loop.rate_hz": -5}, "loop.rate_hz"),
    "loop.rate_hz 500": ({"loop.rate_hz": 500}, "loop.rate_hz"),
    "loop.rate_hz fast": ({"loop.rate_hz": "fast"}, "loop.rate_hz"),
    "loop.rate_hz nan": ({"loop.rate_hz": float("nan")}, "loop.rate_hz"),
    "loop.rate_hz true": ({"loop.rate_hz": True}, "loop.rate_hz"),
    "loop.priority 0": ({"loop.priority": 0}, "loop.priority"),
    "loop.priority 120": ({"loop.priority": 120}, "loop.priority"),
    "loop.priority 5.5": ({"loop.priority": 5.5}, "loop.priority"),
    "loop.sched_fifo 1": ({"loop.sched_fifo": 1}, "loop.sched_fifo"),
    "workers.executor gpu": ({"workers.executor": "gpu"}, "workers.executor"),
    "workers.replan_period -1": ({"workers.replan_period": -1.0}, "workers.replan_period"),
    "workers.refit_period 0": ({"workers.refit_period": 0}, "workers.refit_period"),
    "failsafe.state_max_age below one period": ({"failsafe.state_max_age": 0.04}, "failsafe.state_max_age"),
    "failsafe.stall below two periods": ({"failsafe.stall": 0.09}, "failsafe.stall"),
    "failsafe.overrun_streak 0": ({"failsafe.overrun_streak": 0}, "failsafe.overrun_streak"),
    "failsafe.connect_timeout 0": ({"failsafe.connect_timeout": 0}, "failsafe.connect_timeout"),
    "failsafe.hold -1": ({"failsafe.hold": -1.0}, "failsafe.hold"),
    "route.scenario does not exist": ({"route.scenario": "no_such_route"}, "route.scenario"),
    "route table missing": ({"route": DELETE}, "route"),
    "controller.model missing file": ({"controller.model": "no_such_model.npz"}, "controller.model"),
    "controller.compensation a string": ({"controller.compensation": "yes"}, "controller.compensation"),
    "telemetry.listen not an endpoint": ({"telemetry.listen": ["127.0.0.1:7447"]}, "telemetry.listen"),
    "telemetry.listen not a list": ({"telemetry.listen": "tcp/127.0.0.1:7447"}, "telemetry.listen"),
    "telemetry.listen bad protocol": ({"telemetry.listen": ["http/127.0.0.1:7447"]}, "telemetry.listen"),
    "telemetry.connect bad port": ({"telemetry.connect": ["tcp/127.0.0.1:70000"]}, "telemetry.connect"),
    "telemetry.rate_hz 0": ({"telemetry.rate_hz": 0}, "telemetry.rate_hz"),
    "telemetry.mode unknown": ({"telemetry.mode": "router"}, "telemetry.mode"),
    "telemetry client without connect": ({"telemetry.mode": "client"}, "telemetry.connect"),
    "log.dir not a string": ({"log.dir": 3}, "log.dir"),
    "log.flush_period too short": ({"log.flush_period": 0.01}, "log.flush_period"),
    "log.flush_period too long": ({"log.flush_period": 60.0}, "log.flush_period"),
    "log.flush_period not a number": ({"log.flush_period": "1s"}, "log.flush_period"),
    "description not a string": ({"description": ["x"]}, "description"),
}


@pytest.mark.parametrize("changes, field", LOAD_CASES.values(), ids=LOAD_CASES.keys())
def test_malformed_field_is_named(tmp_path, changes, field):
    f = write_mission(tmp_path, **changes)
    with pytest.raises(ConfigError) as info:
        load_mission(f)
    assert_names(info.value, f, field)


def test_table_that_is_not_a_table_is_named(tmp_path):
    doc = copy.deepcopy(BASE)
    doc["loop"] = 20
    f = write_mission(tmp_path, doc)
    with pytest.raises(ConfigError) as info:
        load_mission(f)
    assert_names(info.value, f, "loop")


BUILD_CASES = {
    # id: (changes, field) -- the mission loads; building the controller or the platform fails
    "controller.name unknown": ({"controller.name": "autopilot"}, "controller.name"),
    "controller.name for the other platform": ({"controller.name": "pd_tracker"}, "controller.name"),
    "controller.compensation with pure_pursuit": ({"controller.name": "pure_pursuit", "controller.compensation": True},
                                                  "controller.compensation"),
    "compensation at a rate that does not divide the model step": ({"controller.compensation": True,
                                                                    "loop.rate_hz": 30}, "loop.rate_hz"),
    "unknown key in platform": ({"platform.physics_rate": 200}, "platform.physics_rate"),
    "platform.physics_rate_hz 5": ({"platform.physics_rate_hz": 5}, "platform.physics_rate_hz"),
    "platform.seed -1": ({"platform.seed": -1}, "platform.seed"),
    "platform.land_speed 0": ({"platform.land_speed": 0}, "platform.land_speed"),
    "platform.hold_s -1": ({"platform.hold_s": -1.0}, "platform.hold_s"),
}


@pytest.mark.parametrize("changes, field", BUILD_CASES.values(), ids=BUILD_CASES.keys())
def test_malformed_field_found_when_building(tmp_path, changes, field):
    f = write_mission(tmp_path, **changes)
    load_mission(f)
    with pytest.raises(ConfigError) as info:
        check(f)
    assert_names(info.value, f, field)


def test_platform_options_are_checked_by_their_driver(tmp_path):
    doc = tomllib.loads(QUAD.read_text())
    f = write_mission(tmp_path, doc, **{"platform.kind": "mavlink"})
    mission = load_mission(f)                    # mavlink fits an aerial route
    with pytest.raises(ConfigError) as info:     # physics_rate_hz belongs to inproc
        build_platform(mission)
    assert_names(info.value, f, "platform.physics_rate_hz")
    f = write_mission(tmp_path, doc, **{"platform": {"kind": "mavlink", "url": "udp:14540"}})
    with pytest.raises(ConfigError) as info:
        build_platform(load_mission(f))
    assert_names(info.value, f, "platform.url")
    f = write_mission(tmp_path, **{"platform": {"kind": "can", "interface": "kvaser"}})
    with pytest.raises(ConfigError) as info:
        build_platform(load_mission(f))
    assert_names(info.value, f, "platform.interface")
    f = write_mission(tmp_path, doc, **{"platform.kind": "can"})   # can drives ground vehicles only
    with pytest.raises(ConfigError) as info:
        load_mission(f)
    assert_names(info.value, f, "platform.kind")


def test_model_that_is_not_a_model(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"\x00garbage, not a zip archive\xff" * 10)
    f = write_mission(tmp_path, **{"controller.model": "bad.npz"})
    mission = load_mission(f)
    assert mission.model_path == bad
    with pytest.raises(ConfigError) as info:
        build_controller(mission)
    # the model's loader names the model file (the file at fault) and its whole-file field
    assert_names(info.value, bad, "<file>")
    assert "not a readable NumPy .npz archive" in str(info.value)


def test_model_for_another_plant(tmp_path):
    f = write_mission(tmp_path, **{"controller.model": "quadrotor.npz"})
    with pytest.raises(ConfigError) as info:
        build_controller(load_mission(f))
    assert info.value.file == str(f)
    assert "lacks the model's" in str(info.value)


def test_toml_syntax_error(tmp_path):
    f = tmp_path / "broken.toml"
    f.write_text(VEHICLE.read_text().replace("rate_hz = 20", "rate_hz = = 20"))
    with pytest.raises(ConfigError) as info:
        load_mission(f)
    assert_names(info.value, f, "<syntax>")
    assert "not valid TOML" in str(info.value) and "line" in str(info.value)


def test_empty_file(tmp_path):
    f = tmp_path / "empty.toml"
    f.write_text("")
    with pytest.raises(ConfigError) as info:
        load_mission(f)
    assert_names(info.value, f, "vehicle_id")
    assert "missing required field" in str(info.value)


def test_missing_file(tmp_path):
    f = tmp_path / "nowhere.toml"
    with pytest.raises(ConfigError) as info:
        load_mission(f)
    assert_names(info.value, f, "<file>")


# Inputs that once raised a traceback instead of exit code 2.
def test_log_flush_period_default_and_set(tmp_path):
    assert load_mission(write_mission(tmp_path)).log_flush_period == 0.5
    assert load_mission(write_mission(tmp_path, **{"log.flush_period": 1})).log_flush_period == 1.0


def test_log_dir_of_an_unknown_user(tmp_path):
    f = write_mission(tmp_path, **{"log.dir": "~no_such_user_vflpcd/logs"})
    with pytest.raises(ConfigError) as info:
        load_mission(f)
    assert_names(info.value, f, "log.dir")


@pytest.mark.parametrize("key, field", [("route.scenario", "route.scenario"), ("controller.model", "controller.model")])
def test_file_name_too_long(tmp_path, key, field):
    f = write_mission(tmp_path, **{key: "x" * 300})
    with pytest.raises(ConfigError) as info:
        load_mission(f)
    assert_names(info.value, f, field)


def test_mission_not_utf8(tmp_path):
    f = tmp_path / "latin1.toml"
    f.write_bytes(VEHICLE.read_bytes().replace(b"in-process", b"in-process \xe9"))
    with pytest.raises(ConfigError) as info:
        load_mission(f)
    assert_names(info.value, f, "<syntax>")


def test_mission_is_a_directory(tmp_path):
    with pytest.raises(ConfigError) as info:
        load_mission(tmp_path)
    assert_names(info.value, tmp_path, "<file>")


# --------------------------------------------------------------------------- the command line
def one_error_line(err: str) -> str:
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("vflpcd: error: "), err
    return lines[0]


def test_cli_check_ok(capsys):
    assert main(["check", str(VEHICLE)]) == 0
    out, err = capsys.readouterr()
    lines = out.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{VEHICLE}: ok: vehicle suv1, inproc platform"), out
    assert "Traceback" not in err


@pytest.mark.parametrize("shipped", MISSIONS, ids=[p.stem for p in MISSIONS])
def test_cli_check_shipped(capsys, shipped):
    assert main(["check", str(shipped)]) == 0
    assert ": ok: " in capsys.readouterr().out


CLI_CASES = {
    "malformed field": ({"loop.rate_hz": "fast"}, "loop.rate_hz"),
    "unknown platform": ({"platform.kind": "rover"}, "platform.kind"),
    "unreadable model file": ({"controller.model": "bad.npz"}, "<file>"),
    "unknown controller": ({"controller.name": "autopilot"}, "controller.name"),
}


@pytest.mark.parametrize("command", ["check", "run"])
@pytest.mark.parametrize("changes, field", CLI_CASES.values(), ids=CLI_CASES.keys())
def test_cli_bad_input_exit_2(tmp_path, capsys, command, changes, field):
    (tmp_path / "bad.npz").write_bytes(b"not a model")
    f = write_mission(tmp_path, **changes)
    assert main([command, str(f)]) == 2
    out, err = capsys.readouterr()
    line = one_error_line(err)
    named = tmp_path / "bad.npz" if field == "<file>" else f
    assert line.startswith(f"vflpcd: error: {named}: {field}: "), line
    assert "Traceback" not in out + err
    assert not (tmp_path / "logs").exists() or not any((tmp_path / "logs").iterdir())


def test_cli_check_names_a_bad_platform_option(tmp_path, capsys):
    f = write_mission(tmp_path, tomllib.loads(QUAD.read_text()), **{"platform.kind": "mavlink"})
    assert main(["check", str(f)]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert line.startswith(f"vflpcd: error: {f}: platform.physics_rate_hz: unknown field (allowed: ")


def test_cli_run_bad_drill(capsys):
    assert main(["run", str(VEHICLE), "--drill", "meteor@3"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert line.startswith("vflpcd: error: command line: --drill: ")


def test_cli_run_port_in_use(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        f = write_mission(tmp_path, **{"telemetry.listen": [f"tcp/127.0.0.1:{port}"]})
        proc = subprocess.run([sys.executable, "-m", "vflpcd.app.cli", "run", str(f)], cwd=ROOT,
                              capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip() and not LOG_LINE.match(ln)]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"vflpcd: error: {f}: telemetry.listen: "), proc.stderr
    assert str(port) in lines[0] and "in use" in lines[0]


# --------------------------------------------------------------------------- random mutations
STRINGS = ["", " ", "~", "~no_such_user_vflpcd/logs", "../", ".", "/", "/tmp", "/dev/null", "*", "a/b", "a b",
           "suv1", "rover", "inproc", "mavlink", "can", "process", "thread", "gpu", "peer", "client", "router",
           "vflpc", "vflpc_ml", "koopman_mpc", "pure_pursuit", "pd_tracker", "autopilot", "carsim_avoidance",
           "racing_track", "dense_static", "uav_3d", "quadrotor.npz", "dynamic_bicycle.npz", "quadrotor",
           "bad.npz", "mission.toml", "tcp/127.0.0.1:0", "tcp/127.0.0.1:99999", "udp/[::1]:7447",
           "tcp/256.1.1.1:80", "tcp/host:7447", "nan", "inf", "é", "\u0000"]

FLOATS = st.one_of(st.sampled_from([0.0, -0.0, -1.0, -5.0, 1e-9, 0.001, 0.049, 0.1, 0.5, 1.0, 19.5, 20.0, 200.0,
                                    200.0001, 1e300, -1e300, math.nan, math.inf, -math.inf]),
                   st.floats(allow_nan=True, allow_infinity=True))
INTS = st.one_of(st.sampled_from([0, -1, 1, 2, 5, 10, 20, 50, 99, 100, 120, 200, 201, 2000, 2001, 65535,
                                  2**63 - 1, -(2**63), 10**30]), st.integers())
TEXT = st.one_of(st.sampled_from(STRINGS), st.text(max_size=12))
KEYS = st.one_of(st.sampled_from(["rat_hz", "kind", "rate_hz", "dir", "model", "extra", "listen", "hold", "seed",
                                  "scenario", "name", "x", ""]), st.text(max_size=8))
SCALARS = st.one_of(INTS, FLOATS, TEXT, st.booleans())
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                      st.dictionaries(KEYS, inner, max_size=3)), max_leaves=6)


def _kind(v) -> str:
    return {bool: "bool", int: "int", float: "float", str: "str", list: "list", dict: "dict"}[type(v)]


OF_KIND = {"int": INTS, "float": FLOATS, "str": TEXT, "bool": st.booleans(),
           "list": st.lists(SCALARS, max_size=3), "dict": st.dictionaries(KEYS, SCALARS, max_size=3)}


def _paths(node, prefix=()):
    """Every (path, value) below node, depth first (dict keys and list indices)."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for k, v in items:
        yield prefix + (k,), v
        yield from _paths(v, prefix + (k,))


def _parent(doc, path):
    node = doc
    for k in path[:-1]:
        node = node[k]
    return node


@st.composite
def mutated_missions(draw):
    doc = copy.deepcopy(BASE)
    for _ in range(draw(st.integers(1, 3))):
        paths = list(_paths(doc))
        if draw(st.booleans()):                   # half the mutations go where the controller is built from
            paths = [(p, v) for p, v in paths if p[0] in ("controller", "route") or p == ("loop", "rate_hz")] or paths
        op = draw(st.sampled_from(["revalue", "revalue", "delete", "retype", "add"]))
        if op == "add" or not paths:
            tables = [()] + [p for p, v in paths if isinstance(v, dict)]
            where = draw(st.sampled_from(tables))
            node = doc
            for k in where:
                node = node[k]
            node[draw(KEYS)] = draw(VALUES)
            continue
        path, old = draw(st.sampled_from(paths))
        parent = _parent(doc, path)
        if op == "delete":
            del parent[path[-1]]
        elif op == "retype":
            kind = draw(st.sampled_from([k for k in OF_KIND if k != _kind(old)]))
            parent[path[-1]] = draw(OF_KIND[kind])
        else:
            parent[path[-1]] = draw(OF_KIND[_kind(old)])
    return doc


def _controller_inputs(doc):
    loop = doc.get("loop")
    rate = loop.get("rate_hz", 50.0) if isinstance(loop, dict) else None
    return doc.get("controller"), doc.get("route"), rate


@pytest.fixture(scope="module")
def mutation_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("mutations")
    (d / "bad.npz").write_bytes(b"not a model")
    return d


@settings(max_examples=150, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(doc=mutated_missions())
def test_mutated_missions_raise_only_config_errors(mutation_dir, doc):
    text = to_toml(doc)
    assert _same(tomllib.loads(text), doc)
    note(text)
    f = mutation_dir / "mission.toml"
    f.write_text(text, encoding="utf-8")
    try:
        mission = load_mission(f)
    except ConfigError as err:
        assert str(err).startswith(f"{err.file}: {err.field}: ")
        event("rejected by load_mission")
        return
    try:
        if not _same(_controller_inputs(doc), _controller_inputs(BASE)):
            event("controller built")
            build_controller(mission)             # otherwise: the shipped mission's, known to build
        build_platform(mission)
    except ConfigError as err:
        assert str(err).startswith(f"{err.file}: {err.field}: ")
        event("rejected when building")
    else:
        event("accepted")
