"""systemd/vflpcd@.service against the daemon's shutdown: TimeoutStopSec leaves room for the
longest wait for rest (the default failsafe.land_timeout, and every shipped mission's) plus the
closing steps, and the exit codes that must not restart the daemon are the service's."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from vflpcd.daemon.config import FailsafePolicy
from vflpcd.daemon.service import EXIT_BAD_INPUT, EXIT_COLLISION, EXIT_FAILSAFE, EXIT_NOT_AT_REST
from vflpcd.config.mission import load_mission

ROOT = Path(__file__).resolve().parents[3]
UNIT = ROOT / "systemd" / "vflpcd@.service"
CLOSE_MARGIN_S = 5.0           # the shutdown steps after the wait (about 3 s), with room to spare


def setting(key: str) -> str:
    (value,) = [line.split("=", 1)[1].strip() for line in UNIT.read_text().splitlines()
                if line.startswith(f"{key}=")]
    return value


def seconds(value: str) -> float:
    m = re.fullmatch(r"(\d+(?:\.\d+)?)(s|min)?", value)
    assert m, f"unexpected time span {value!r}"
    return float(m.group(1)) * (60.0 if m.group(2) == "min" else 1.0)


def rest_timeout(policy: FailsafePolicy) -> float:
    return max(policy.land_timeout, policy.brake_timeout)


def test_timeout_stop_sec_fits_the_default_landing():
    assert seconds(setting("TimeoutStopSec")) >= rest_timeout(FailsafePolicy()) + CLOSE_MARGIN_S


@pytest.mark.parametrize("mission", sorted((ROOT / "config" / "missions").glob("*.toml")), ids=lambda p: p.name)
def test_timeout_stop_sec_fits_each_shipped_mission(mission):
    assert seconds(setting("TimeoutStopSec")) >= rest_timeout(load_mission(mission).failsafe) + CLOSE_MARGIN_S


def test_no_restart_after_bad_input_a_failsafe_a_vehicle_not_at_rest_or_a_collision():
    assert {EXIT_BAD_INPUT, EXIT_FAILSAFE, EXIT_NOT_AT_REST, EXIT_COLLISION} <= set(map(int, setting("RestartPreventExitStatus").split()))
