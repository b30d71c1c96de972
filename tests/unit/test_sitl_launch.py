"""`vflpcd run --with-sitl`: which mocks a mission gets."""

import sys

import pytest

from vflpcd.base.errors import ConfigError
from vflpcd.config.mission import load_mission
from vflpcd.base.paths import config_dir
from vflpcd.app.sitl_launch import SitlProcesses

MISSIONS = config_dir() / "missions"


def test_can_on_a_remote_bus_gets_the_hub_and_the_ecu(tmp_path):
    cmds = SitlProcesses(load_mission(MISSIONS / "vehicle_can.toml"), tmp_path).commands
    (hub, hub_argv, address), (ecu, ecu_argv, _) = cmds
    assert hub == "hub" and hub_argv[:3] == [sys.executable, "-m", "can_remote"] and address == ("127.0.0.1", 54701)
    assert ecu == "ecu" and ecu_argv[-3:] == ["sitl", "can-ecu", str(MISSIONS / "vehicle_can.toml")]


def test_mavlink_gets_the_autopilot_on_the_mission_port(tmp_path):
    ((name, argv, _),) = SitlProcesses(load_mission(MISSIONS / "quad_sitl.toml"), tmp_path).commands
    assert name == "quad" and argv[-6:] == ["sitl", "quad", "--host", "127.0.0.1", "--port", "14540"]


@pytest.mark.parametrize("mission, field", [("vehicle_inproc.toml", "platform.kind")])
def test_missions_without_a_mock_are_refused(tmp_path, mission, field):
    with pytest.raises(ConfigError) as err:
        SitlProcesses(load_mission(MISSIONS / mission), tmp_path)
    assert err.value.field == field


def test_a_virtual_bus_is_refused(tmp_path):
    text = (MISSIONS / "vehicle_can.toml").read_text().replace('interface = "remote"', 'interface = "virtual"')
    (tmp_path / "m.toml").write_text(text)
    with pytest.raises(ConfigError) as err:
        SitlProcesses(load_mission(tmp_path / "m.toml"), tmp_path)
    assert err.value.field == "platform.interface"
