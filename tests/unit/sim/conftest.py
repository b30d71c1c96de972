"""Shared fixtures of the sim tests."""

import pytest

from vflpcd.config.scenarios import line_scenario_toml, load_scenario


@pytest.fixture
def line_scenario(tmp_path):
    """A ground scenario on the straight line (0, 0) -> (length, 0), written to tmp_path and loaded;
    ``obstacles`` is TOML text of [[obstacles]] tables."""

    def build(name: str = "line", **options):
        f = tmp_path / f"{name}.toml"
        f.write_text(line_scenario_toml(name, **options))
        return load_scenario(f)

    return build
