"""A VF-LPC controller and its car at the start of a straight road (``line_scenario_toml``)."""

from pathlib import Path


def vflpc_on_a_line(folder: Path, length: float, speed: float, t_max: float = 60.0, stop: bool = False):
    """(scenario, controller, plant) for a road of ``length`` m driven at ``speed`` m/s (``stop``: its
    end is a stop, else the road runs on past it), its file in ``folder``."""
    from sim.plants import make_plant
    from vflpcd.config.scenarios import line_scenario_toml, load_scenario
    from vflpcd.controllers.vflpc import make_vflpc

    f = folder / "line.toml"
    f.write_text(line_scenario_toml("line", length=length, speed=speed, t_max=t_max, stop=stop))
    sc = load_scenario(f)
    return sc, make_vflpc(sc), make_plant(sc, 0)
