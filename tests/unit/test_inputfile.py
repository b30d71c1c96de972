"""Input files that cannot hurt (``vflpcd.base.inputfile``): only regular files under a size limit
are read, never more than the limit, never blocking; TOML and JSON nest at most MAX_DEPTH deep;
every failure is one ConfigError line naming the file. A property test feeds the loaders random,
truncated, deeply nested, non-UTF-8 and special files: a ConfigError or a result, nothing else,
and never a hang."""

from __future__ import annotations

import json
import os
import signal
import socket
import tomllib
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, note, settings
from hypothesis import strategies as st

from vflpcd.base import inputfile
from vflpcd.base.errors import ConfigError
from vflpcd.base.inputfile import (MAX_DEPTH, TEXT_MAX_BYTES, check_depth, open_npz, parse_json, read_bytes,
                                   read_text)
from vflpcd.base.paths import config_dir
from vflpcd.base.tomlread import load_toml
from vflpcd.config.koopman_file import load_koopman
from vflpcd.config.mission import load_mission
from vflpcd.config.scenarios import load_scenario
from vflpcd.config.vehicles import BicycleConfig
from vflpcd.controllers.pure_pursuit import PurePursuitGains
from vflpcd.training.datasets import Log, load_log, save_log
from drivers.can_vehicle import can_vehicle_from_scenario

MISSION = config_dir() / "missions" / "vehicle_inproc.toml"
SCENARIO = config_dir() / "scenarios" / "dense_static.toml"
MODEL = config_dir() / "models" / "dynamic_bicycle.npz"
DBC = config_dir() / "can" / "vehicle.dbc"


class Hang(BaseException):
    """A read that did not come back (a BaseException: no loader's ``except Exception`` hides it)."""


@contextmanager
def no_hang(seconds: float = 5.0):
    def expire(signum, frame):
        raise Hang(f"no answer within {seconds} s")
    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def one_line(err: ConfigError, file: Path | str) -> str:
    text = str(err)
    assert len(text.splitlines()) == 1, text
    assert text.startswith(f"{file}: "), text
    return text


def refused(call, path, *args, **kwargs) -> ConfigError:
    with no_hang(), pytest.raises(ConfigError) as info:
        call(path, *args, **kwargs)
    one_line(info.value, path)
    return info.value


# --------------------------------------------------------------------------- what is refused
def special_files(folder: Path) -> dict[str, tuple[Path, str]]:
    """name -> (path, the kind the error names)."""
    fifo = folder / "fifo.toml"
    os.mkfifo(fifo)
    out = {"directory": (folder, "a directory"), "fifo": (fifo, "a FIFO"),
           "/dev/zero": (Path("/dev/zero"), "a character device"),
           "/dev/null": (Path("/dev/null"), "a character device")}
    for name, (target, kind) in list(out.items()):
        link = folder / f"link-{name.strip('/').replace('/', '-')}.toml"
        link.symlink_to(target)
        out[f"link to {name}"] = (link, kind)
    return out


def test_special_files_are_refused_unread(tmp_path):
    for name, (path, kind) in special_files(tmp_path).items():
        err = refused(read_bytes, path)
        assert err.field == "<file>" and err.message == f"not a regular file ({kind})", name


def test_a_socket_is_refused(tmp_path):
    path = tmp_path / "s"
    with socket.socket(socket.AF_UNIX) as s:
        try:
            s.bind(str(path))
        except OSError:                             # a temporary folder too deep for a socket's name
            pytest.skip("socket path too long")
        assert refused(read_bytes, path).message == "not a regular file (a socket)"


@pytest.mark.parametrize("name, message", [
    ("nowhere.toml", "file not found"),
    ("dangling.toml", "file not found"),
    ("loop.toml", "cannot read (Too many levels of symbolic links)"),
    ("plain.toml/x.toml", "cannot read (Not a directory)"),
    ("nul\0.toml", "cannot read (embedded null byte)"),
    ("x" * 300 + ".toml", "cannot read (File name too long)"),
])
def test_paths_that_lead_nowhere(tmp_path, name, message):
    (tmp_path / "dangling.toml").symlink_to(tmp_path / "gone")
    (tmp_path / "loop.toml").symlink_to(tmp_path / "loop.toml")
    (tmp_path / "plain.toml").write_text("")
    assert refused(read_text, tmp_path / name).message == message


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads every file")
def test_unreadable_file(tmp_path):
    f = tmp_path / "secret.toml"
    f.write_text("x = 1\n")
    f.chmod(0)
    assert refused(load_toml, f).message == "cannot read (Permission denied)"


def test_size_limit_is_checked_before_reading(tmp_path):
    f = tmp_path / "big.toml"
    with f.open("wb") as fh:
        fh.truncate(TEXT_MAX_BYTES + 1)            # sparse: nothing to read but its size
    assert refused(load_toml, f).message == f"too large ({TEXT_MAX_BYTES + 1} bytes, the limit is {TEXT_MAX_BYTES})"
    f.write_bytes(b"x" * 100)
    assert read_bytes(f, limit=100) == b"x" * 100
    assert refused(read_bytes, f, limit=99).message == "too large (100 bytes, the limit is 99)"


def test_no_more_than_the_limit_is_read_from_a_file_that_says_it_is_empty():
    # /proc files are regular files of size 0 that read as text: the size is not trusted
    status = Path("/proc/self/status")
    assert status.stat().st_size == 0 and len(read_bytes(status)) > 100
    assert refused(read_bytes, status, limit=100).message == "too large (more than 100 bytes)"


def test_text_must_decode(tmp_path):
    f = tmp_path / "latin1.toml"
    f.write_bytes(b'name = "caf\xe9"\n')
    err = refused(load_toml, f)
    assert err.field == "<syntax>" and err.message.startswith("not UTF-8 text (invalid continuation byte at byte 11")
    assert read_text(f, encoding="cp1252") == 'name = "café"\n'
    f.write_bytes(b"\x81")                          # undefined in cp1252
    assert refused(read_text, f, encoding="cp1252").message.startswith("not CP1252 text")


def test_line_breaks_in_a_name_stay_on_one_line(tmp_path):
    f = tmp_path / "two\nlines\u2028.toml"
    with pytest.raises(ConfigError) as info:
        load_toml(f)
    assert info.value.file == str(tmp_path) + r"/two\nlines\u2028.toml"   # as it is printed: one line
    assert str(info.value) == str(tmp_path) + r"/two\nlines\u2028.toml: <file>: file not found"


# --------------------------------------------------------------------------- nesting
def nested(depth: int, kind: str) -> str:
    if kind == "array":
        return "x = " + "[" * depth + "]" * depth + "\n"
    return "x = " + "{a = " * depth + "1" + " }" * depth + "\n"


@pytest.mark.parametrize("kind", ["array", "inline table"])
def test_nesting_up_to_the_limit_parses_and_deeper_is_refused(tmp_path, kind):
    f = tmp_path / "deep.toml"
    f.write_text(nested(MAX_DEPTH, kind))
    assert "x" in load_toml(f)
    for depth in (MAX_DEPTH + 1, 5000, 100_000):
        f.write_text("a = 1\n" + nested(depth, kind))
        err = refused(load_toml, f)
        assert err.field == "<syntax>" and err.message == f"nested deeper than {MAX_DEPTH} arrays or tables (line 2)"


def test_brackets_in_strings_and_comments_do_not_nest():
    many = "[{" * 100
    text = "\n".join([
        f'a = "{many}\\"{many}"', f"b = '{many}'", f'c = """{many}\n"{many}""{many}\\"""{many}"""""',
        f"d = '''{many}\n'{many}''{many}'''''", f"# {many}", f'"{many}" = 1', f'e = [ # {many}', "1]",
        "[[f]]", "[g.h]", nested(MAX_DEPTH, "array")])
    doc = tomllib.loads(text)
    assert doc["c"].endswith(many + '""') and doc["d"].endswith(many + "''")
    check_depth(text, "t.toml")
    with pytest.raises(ConfigError, match=r"\(line 14\)$"):
        check_depth(text + nested(MAX_DEPTH + 1, "array"), "t.toml")


def _depth(v) -> int:
    if isinstance(v, list):
        return 1 + max(map(_depth, v), default=0)
    if isinstance(v, dict):
        return 1 + max(map(_depth, v.values()), default=0)
    return 0


TRICKY = st.text(alphabet="[]{}\"'#\\\n ab", max_size=8)
JSON_VALUES = st.recursive(st.one_of(st.integers(), TRICKY, st.booleans()),
                           lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                   st.dictionaries(TRICKY, inner, max_size=3)), max_leaves=40)


@settings(max_examples=150, deadline=None, derandomize=True, database=None)
@given(value=JSON_VALUES, limit=st.integers(0, 6))
def test_the_depth_scan_counts_what_the_parser_nests(value, limit):
    """JSON text (whose strings are TOML basic strings): refused exactly when it nests deeper than
    the limit, whatever brackets, quotes and hashes its strings hold."""
    text = json.dumps(value, ensure_ascii=False)
    try:
        check_depth(text, "v.json", limit=limit)
    except ConfigError:
        assert _depth(value) > limit
    else:
        assert _depth(value) <= limit


def test_json_errors(tmp_path):
    assert parse_json('{"a": [1]}', "m.json") == {"a": [1]}
    with pytest.raises(ConfigError, match=r"^m.json: metadata: not valid JSON \(Expecting value at line 2\)$"):
        parse_json('{"a":\n}', "m.json", "metadata")
    with pytest.raises(ConfigError, match=f"nested deeper than {MAX_DEPTH}"):
        parse_json("[" * 100_000 + "]" * 100_000, "m.json")


# --------------------------------------------------------------------------- .npz archives
def test_npz_archives(tmp_path):
    good = tmp_path / "good.npz"
    np.savez(good, a=np.arange(3.0))
    with open_npz(good) as npz:
        assert list(npz["a"]) == [0.0, 1.0, 2.0]
    single = tmp_path / "single.npz"
    with single.open("wb") as fh:
        np.save(fh, np.zeros(3))
    assert refused(load_koopman, single).message == "not a readable NumPy .npz archive (a single .npy array)"
    pickled = tmp_path / "pickled.npz"
    np.savez(pickled, a=np.array([{"x": 1}], dtype=object))
    with open_npz(pickled) as npz, pytest.raises(ValueError, match="pickle"):
        npz["a"]                                    # refused by numpy; load_koopman names the key
    bomb = tmp_path / "bomb.npz"
    np.savez_compressed(bomb, a=np.zeros(10**6))   # 8 MB of zeros in a few kB
    assert bomb.stat().st_size < 100_000
    with pytest.raises(ConfigError, match=r"too large unpacked \(8000\d+ bytes, the limit is 100000\)"), \
            open_npz(bomb, limit=100_000):
        pass


def test_model_metadata_nested_too_deeply(tmp_path):
    arrays = dict(np.load(MODEL, allow_pickle=False))
    arrays["metadata"] = np.array("[" * 5000 + "]" * 5000)
    bad = tmp_path / "deep.npz"
    np.savez(bad, **arrays)
    err = refused(load_koopman, bad)
    assert err.field == "metadata" and err.message.startswith("nested deeper than")


# --------------------------------------------------------------------------- the loaders, at random
SCENE = load_scenario("carsim_avoidance")
LOADERS = {                                         # name -> (load(path), a valid file's suffix)
    "mission": (load_mission, ".toml"),
    "scenario": (load_scenario, ".toml"),
    "plant": (lambda p: BicycleConfig.load("nominal", p), ".toml"),
    "controller": (PurePursuitGains.load, ".toml"),
    "model": (load_koopman, ".npz"),
    "training log": (load_log, ".npz"),
    "dbc": (lambda p: can_vehicle_from_scenario(SCENE, {"dbc": str(p)}, "m.toml"), ".dbc"),
}
SPECIAL = ("directory", "fifo", "link to /dev/zero", "link to fifo", "dangling link")


@st.composite
def inputs(draw):
    """(loader name, what the file is, how to make it from the loader's valid file)."""
    name = draw(st.sampled_from(sorted(LOADERS)))
    how = draw(st.sampled_from(["random bytes", "truncated", "flipped byte", "not UTF-8", "deep arrays",
                                "deep inline tables", "special"]))
    if how == "random bytes":
        return name, how, draw(st.binary(max_size=200))
    if how in ("truncated", "flipped byte"):
        return name, how, (draw(st.integers(0, 10**6)), draw(st.integers(1, 255)))
    if how == "not UTF-8":
        return name, how, (draw(st.integers(0, 10**6)), draw(st.sampled_from([b"\xff", b"\xc3", b"\xed\xa0\x80"])))
    if how.startswith("deep"):
        return name, how, draw(st.sampled_from([MAX_DEPTH, MAX_DEPTH + 1, 400, 5000, 50_000]))
    return name, draw(st.sampled_from(SPECIAL)), None


def make(valid: bytes, how: str, how_much) -> bytes | None:
    if how == "random bytes":
        return how_much
    if how == "truncated":
        return valid[:how_much[0] % (len(valid) + 1)]
    if how == "flipped byte":
        i = how_much[0] % len(valid)
        return valid[:i] + bytes([valid[i] ^ how_much[1]]) + valid[i + 1:]
    if how == "not UTF-8":
        i = how_much[0] % (len(valid) + 1)
        return valid[:i] + how_much[1] + valid[i:]
    if how.startswith("deep"):
        return valid + b"\n" + nested(how_much, "array" if how == "deep arrays" else "inline table").encode()
    return None


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("inputs")
    os.mkfifo(d / "fifo")
    log = Log("run", np.zeros((20, 3)), np.zeros((20, 2)), 0.05, ("X", "Y", "yaw"), ("u1", "u2"))
    valid = {"mission": MISSION.read_bytes(), "scenario": SCENARIO.read_bytes(), "model": MODEL.read_bytes(),
             "plant": (config_dir() / "plants" / "dynamic_bicycle.toml").read_bytes(),
             "controller": (config_dir() / "controllers" / "pure_pursuit.toml").read_bytes(),
             "training log": save_log(log, d / "log.npz").read_bytes(), "dbc": DBC.read_bytes()}
    return d, valid


def place(folder: Path, suffix: str, how: str, data: bytes | None) -> Path:
    f = folder / f"input{suffix}"
    if f.is_symlink() or f.exists():
        f.unlink()
    if data is not None:
        f.write_bytes(data)
        return f
    target = {"directory": folder, "fifo": folder / "fifo", "link to /dev/zero": Path("/dev/zero"),
              "link to fifo": folder / "fifo", "dangling link": folder / "gone"}[how]
    if how in ("directory", "fifo"):
        return target
    f.symlink_to(target)
    return f


@settings(max_examples=250, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(case=inputs())
def test_loaders_give_a_config_error_or_a_result_never_anything_else(fuzz_dir, case):
    folder, valid = fuzz_dir
    name, how, how_much = case
    load, suffix = LOADERS[name]
    path = place(folder, suffix, how, make(valid[name], how, how_much))
    note(f"{name}: {how}")
    try:
        with no_hang(5.0):
            load(path)
    except ConfigError as err:
        text = str(err)
        assert len(text.splitlines()) == 1, text
        assert str(path) in text or (name == "dbc" and text.startswith("m.toml: platform.dbc: ")), text
        event(f"{how}: refused")
    else:
        # what may still be valid: a file cut at its end or changed where nothing reads, an
        # archive with bytes after its end
        assert how in ("truncated", "flipped byte", "not UTF-8") or (how.startswith("deep") and suffix == ".npz"), how
        event(f"{how}: accepted")


def test_every_reader_goes_through_inputfile():
    """No reader of a user's file opens it by itself (the Python parsers' entry points on files)."""
    root = Path(__file__).resolve().parents[2]
    patterns = ("tomllib.load(", "json.load(", "np.load(", "cantools.database.load_file(", "np.loadtxt(path",
                ".read_text(", ".read_bytes(", "open(path")
    found = []
    for folder in ("vflpcd", "drivers"):
        for py in (root / folder).rglob("*.py"):
            if py.name == "inputfile.py":
                continue
            text = py.read_text()
            found += [f"{py.relative_to(root)}: {p}" for p in patterns if p in text]
    allowed = {"vflpcd/controllers/compiled.py: .read_bytes(",     # the project's own C source
               "vflpcd/controllers/loop_cache.py: .read_bytes(",   # the project's own Python sources
               "vflpcd/controllers/loop_cache.py: .read_text(",
               "vflpcd/app/steal.py: open(path"}                   # the kernel's /proc/stat, not a user's file
    assert set(found) <= allowed, sorted(set(found) - allowed)
