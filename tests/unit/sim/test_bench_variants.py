"""The road variants of `vflpcd bench variants`: seeded, valid scenarios with moving obstacles."""

import numpy as np

from sim.bench.variants import variant_toml
from vflpcd.config.scenarios import load_scenario


def test_variants_are_seeded_valid_and_move(tmp_path):
    assert variant_toml(3) == variant_toml(3) and variant_toml(3) != variant_toml(4)
    kinds = set()
    for seed in range(20):
        f = tmp_path / f"v{seed}.toml"
        f.write_text(variant_toml(seed))
        sc = load_scenario(f)
        ids = [o.id for o in sc.obstacles]
        assert ids[:2] == ["pedestrian", "slow_car"]
        kinds.add(len(ids))
        ped, car = sc.obstacles[0], sc.obstacles[1]
        assert 0.8 <= np.linalg.norm(ped.velocity) <= 1.8 and ped.trigger == "move"
        assert np.sign(ped.velocity[1]) == -np.sign(ped.center[1])   # it crosses the road
        assert 1.0 <= car.velocity[0] <= 3.0 and car.velocity[1] == 0.0
    assert kinds == {2, 3}                                            # with and without the barrel
