"""Nothing outlives ``vflpcd run``: its two worker processes and the multiprocessing resource
tracker end with it, when it is SIGKILLed as when it stops on SIGTERM; and ``Proc.kill()`` (for
the tests that SIGKILL a daemon) finds none of them left."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from loopback import free_port
from processes import ROOT, Proc, descendants, session_members

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads processes from /proc")

GONE_WITHIN_S = 2.0        # after the daemon's exit: the workers' lifeline polls every 0.05 s; the tracker then reads EOF


def vehicle_mission(tmp_path: Path) -> Path:
    text = (ROOT / "config/missions/vehicle_inproc.toml").read_text()
    mission = tmp_path / "vehicle.toml"
    mission.write_text(text.replace("7447", str(free_port()))
                       .replace('dir = "logs"', f'dir = "{tmp_path / "logs"}"'))
    return mission


def wait_ready(proc: subprocess.Popen, err: Path, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while "event=ready" not in err.read_text(errors="replace"):
        assert proc.poll() is None and time.monotonic() < deadline, err.read_text()[-2000:]
        time.sleep(0.1)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["sigkill", "sigterm"])
def test_no_process_of_the_daemon_outlives_it(tmp_path, sig):
    err = tmp_path / "daemon.err"
    with open(err, "wb") as f:          # its own session: whatever it starts can be found by sid
        proc = subprocess.Popen([sys.executable, "-m", "vflpcd.app.cli", "run", str(vehicle_mission(tmp_path))],
                                cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=f,
                                start_new_session=True)
    sid = proc.pid
    try:
        wait_ready(proc, err, 90.0)
        below = descendants(proc.pid)
        workers = [p for p in below if "multiprocessing.spawn" in p.cmdline]
        trackers = [p for p in below if "multiprocessing.resource_tracker" in p.cmdline]
        assert len(workers) == 2 and len(trackers) == 1, below
        assert all(p.ppid == proc.pid and p.session == sid for p in below), below

        t_signal = time.monotonic()
        os.kill(proc.pid, sig)
        rc = proc.wait(10.0)          # on SIGTERM the daemon first brakes the car to rest (about 1-3 s)
        t_exit = time.monotonic()
        while session_members(sid) and time.monotonic() < t_exit + GONE_WITHIN_S:
            time.sleep(0.01)
        gone_s = time.monotonic() - t_exit
        left = session_members(sid)
        assert rc == (-signal.SIGKILL if sig == signal.SIGKILL else 0), err.read_text()[-2000:]
        assert not left, f"{len(left)} processes left {gone_s:.2f} s after the daemon's exit on {sig.name}: {left}"
        assert not any(p.alive() for p in below)
        print(f"{sig.name}: daemon gone {t_exit - t_signal:.3f} s after the signal, "
              f"its {len(below)} processes {gone_s:.3f} s after it")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5.0)
        try:
            os.killpg(sid, signal.SIGKILL)          # whatever this test would otherwise leave behind
        except ProcessLookupError:
            pass


def test_proc_kill_sees_the_daemon_and_its_workers_gone(tmp_path):
    daemon = Proc("run", str(vehicle_mission(tmp_path)))
    try:
        daemon.wait_line("event=ready", 90)
        below = descendants(daemon.p.pid)
        assert len(below) == 3, below                 # two workers and the resource tracker
        lingered = daemon.kill(timeout=GONE_WITHIN_S)
        assert daemon.p.returncode == -signal.SIGKILL
        assert lingered == [] and not any(p.alive() for p in below), lingered
    finally:
        daemon.stop()
