"""Simulated plants; ``make_plant`` builds the one a scenario names."""

from __future__ import annotations


def make_plant(scenario, seed: int | None = None):
    """The scenario's plant at its start state (process noise seeded by ``seed`` when enabled)."""
    if scenario.plant == "dynamic_bicycle":
        from sim.plants.dynamic_bicycle import DynamicBicycle
        from vflpcd.config.vehicles import BicycleConfig

        return DynamicBicycle(BicycleConfig.load(scenario.params), scenario.start,
                              process_noise=scenario.process_noise, seed=seed)
    if scenario.plant == "quadrotor":
        from sim.plants.quadrotor import Quadrotor
        from vflpcd.config.vehicles import QuadrotorParams

        return Quadrotor(QuadrotorParams.from_toml(), scenario.start, seed=seed)
    raise ValueError(f"unknown plant {scenario.plant!r}")
