"""``vflpcd check`` on harmful files: an endless device, a FIFO without a writer, a mission
nested 5,000 deep, a 100 MB file. Each is exit code 2 and one line naming the file, quickly and in
little memory (the peak resident size of that process alone, as its parent sees it)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from vflpcd.base.inputfile import MAX_DEPTH, TEXT_MAX_BYTES
from vflpcd.base.paths import config_dir

ROOT = Path(__file__).resolve().parents[2]
MISSION = config_dir() / "missions" / "vehicle_inproc.toml"
MAX_SECONDS = 2.0
MAX_RSS = 200 * 2**20
ADDRESS_SPACE = 4 * 2**30          # a child that regressed runs out of memory here, not the machine

# Started from a small Python rather than from the test process: a child's peak resident size
# (ru_maxrss) counts the memory of the process it was forked from, and pytest's is large.
MEASURE = """
import json, resource, subprocess, sys, time
resource.setrlimit(resource.RLIMIT_AS, (int(sys.argv[1]), int(sys.argv[1])))
start = time.monotonic()
try:
    rc = subprocess.run(sys.argv[3:], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                        timeout=float(sys.argv[2])).returncode
except subprocess.TimeoutExpired:
    rc = None
print(json.dumps({"rc": rc, "wall": time.monotonic() - start,
                  "rss": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024}))
"""


def measured(*argv: str, timeout: float = 10.0) -> tuple[int | None, str, float, int]:
    """``argv`` run: exit code (None when it was killed after ``timeout`` s), stderr, wall time
    (s) and peak resident size (bytes) of that process alone."""
    r = subprocess.run([sys.executable, "-c", MEASURE, str(ADDRESS_SPACE), str(timeout), *argv],
                       cwd=ROOT, capture_output=True, text=True, timeout=timeout + 30.0)
    m = json.loads(r.stdout)
    return m["rc"], r.stderr, m["wall"], m["rss"]


def run_check(path: Path) -> tuple[int | None, str, float, int]:
    return measured(sys.executable, "-m", "vflpcd", "check", str(path))


def _fifo(tmp_path: Path) -> Path:
    path = tmp_path / "mission.toml"
    os.mkfifo(path)
    return path


def _deep(tmp_path: Path) -> Path:
    path = tmp_path / "deep.toml"
    path.write_text("deep = " + "[" * 5000 + "]" * 5000 + "\n" + MISSION.read_text())
    return path


def _deep_tables(tmp_path: Path) -> Path:
    path = tmp_path / "deep_tables.toml"
    path.write_text("deep = " + "{a = " * 5000 + "1" + "}" * 5000 + "\n" + MISSION.read_text())
    return path


def _huge(tmp_path: Path) -> Path:
    path = tmp_path / "huge.toml"
    with path.open("wb") as fh:
        fh.truncate(100_000_000)
    return path


CASES = {
    "/dev/zero": (lambda tmp_path: Path("/dev/zero"), "<file>: not a regular file (a character device)"),
    "FIFO": (_fifo, "<file>: not a regular file (a FIFO)"),
    "5,000-deep array": (_deep, f"<syntax>: nested deeper than {MAX_DEPTH} arrays or tables (line 1)"),
    "5,000-deep inline table": (_deep_tables, f"<syntax>: nested deeper than {MAX_DEPTH} arrays or tables (line 1)"),
    "100 MB": (_huge, f"<file>: too large (100000000 bytes, the limit is {TEXT_MAX_BYTES})"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_check_refuses_a_harmful_file_quickly_in_one_line(tmp_path, case):
    make, message = CASES[case]
    path = make(tmp_path)
    rc, err, wall, rss = run_check(path)
    assert rc == 2, err
    assert err.splitlines() == [f"vflpcd: error: {path}: {message}"], err
    assert wall < MAX_SECONDS, f"{wall:.2f} s"
    assert 10 * 2**20 < rss < MAX_RSS, f"{rss / 2**20:.0f} MiB"     # a Python with numpy, measured



def test_the_measure_sees_a_process_that_takes_memory_or_time():
    rc, _, _, rss = measured(sys.executable, "-c", "b = b'x' * (250 * 2**20)")
    assert rc == 0 and rss > 250 * 2**20
    rc, _, wall, _ = measured(sys.executable, "-c", "import time; time.sleep(60)", timeout=1.0)
    assert rc is None and 1.0 <= wall < 10.0
