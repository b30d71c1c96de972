"""Shared fixtures of the sim tests."""

import pytest

from sim.scenarios import load_scenario

LINE_SCENARIO = """
name = "{name}"
platform = "ground"
control_period = 0.05
t_max = {t_max}
[vehicle]
plant = "dynamic_bicycle"
[path]
kind = "line"
start = [0.0, 0.0]
end = [{length}, 0.0]
[start]
position = [0.0, {y0}]
speed = {speed}
[speed]
desired = {speed}
a_lat_max = {a_lat_max}
[goal]
tolerance = 1.0
[metrics]
q1 = 1.0
q2 = 1.0
R = [[0.1, 0.0], [0.0, 1.0]]
{obstacles}
"""


@pytest.fixture
def line_scenario(tmp_path):
    """A ground scenario on the straight line (0, 0) -> (length, 0), written to tmp_path and loaded;
    ``obstacles`` is TOML text of [[obstacles]] tables."""

    def build(name: str = "line", *, length: float = 60.0, y0: float = 0.0, speed: float = 5.0,
              a_lat_max: float = 3.0, t_max: float = 20.0, obstacles: str = ""):
        f = tmp_path / f"{name}.toml"
        f.write_text(LINE_SCENARIO.format(name=name, length=length, y0=y0, speed=speed, a_lat_max=a_lat_max,
                                          t_max=t_max, obstacles=obstacles))
        return load_scenario(f)

    return build
