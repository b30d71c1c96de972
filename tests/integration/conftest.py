"""Fixtures of the integration tests: short missions for the daemon, written to a temporary folder."""

from __future__ import annotations


import pytest
from pathlib import Path

from loopback import free_port
from vflpcd.config.scenarios import line_scenario_toml


def write_mission(folder: Path, *, route: str | None = None, length: float = 200.0, rate_hz: float = 50.0,
                  executor: str = "thread", telemetry_port: int | None = None, hold: float = 1.5,
                  extra: str = "", platform_extra: str = "", compensation: bool = False,
                  telemetry_extra: str = "", state_max_age: float = 0.5, sched_fifo: bool = True) -> Path:
    """A mission on a straight road of ``length`` m (or the named ``route``), in-process vehicle,
    VF-LPC; telemetry on ``telemetry_port`` (off without one); logs in folder/logs. ``state_max_age``:
    0.5 s unless a test is about stale states: a test process shares two cores with the suite's
    other workers, and at 0.25 s a loaded run's in-process vehicle went 273 ms without a state,
    so that the stale-state failsafe came before the monitor the test was about.
    ``sched_fifo``: the control thread asks for SCHED_FIFO, as a vehicle's unit grants it, so that the
    suite's other workers, three on two cores, do not starve a real-time loop into the overrun and
    stall monitors (where it is not permitted the loop runs with normal scheduling and a warning)."""
    if route is None:
        (folder / "line.toml").write_text(line_scenario_toml("line", length=length, speed=5.0, t_max=200.0))
        route = "line.toml"
    telemetry = (f'[telemetry]\nenabled = true\nlisten = ["tcp/127.0.0.1:{telemetry_port}"]\nrate_hz = 20.0\n{telemetry_extra}\n'
                 if telemetry_port else "[telemetry]\nenabled = false\n")
    text = f"""vehicle_id = "t1"
[platform]
kind = "inproc"
{platform_extra}
[route]
scenario = "{route}"
[controller]
name = "vflpc"
compensation = {str(compensation).lower()}
[loop]
rate_hz = {rate_hz}
sched_fifo = {str(sched_fifo).lower()}
[workers]
executor = "{executor}"
{telemetry}
[failsafe]
state_max_age = {state_max_age}
overrun_streak = 5
stall = 0.4
hold = {hold}
[log]
dir = "{folder / 'logs'}"
{extra}"""
    path = folder / "mission.toml"
    path.write_text(text)
    return path


@pytest.fixture
def mission_file(tmp_path):
    """write_mission bound to the test's temporary folder."""
    return lambda **options: write_mission(tmp_path, **options)


@pytest.fixture
def port():
    return free_port()
