"""The jittered copies of `vflpcd bench jitter`: faithful TOML, seeded, bounded moves in the route's frame."""

import json
import tomllib

import numpy as np
import pytest

from sim.bench.jitter import bench_jitter, jittered, jittered_scene, toml_text
from sim.bench.suite import suite_dir, suite_names
from vflpcd.config.scenarios import load_scenario


@pytest.mark.parametrize("name", suite_names())
def test_every_suite_scene_comes_back_from_its_toml_text(name):
    doc = tomllib.loads((suite_dir() / f"{name}.toml").read_text())
    assert tomllib.loads(toml_text(doc)) == doc


def test_a_copy_at_scale_zero_is_the_scene():
    source = suite_dir() / "bend_obstacle_outside.toml"
    doc = tomllib.loads(source.read_text())
    copy = jittered(doc, load_scenario(source).path, np.random.default_rng(1), 0.0)
    for a, b in zip(doc["obstacles"], copy["obstacles"]):
        np.testing.assert_allclose(b["center"], a["center"], atol=1e-3)
    assert copy["speed"] == doc["speed"]


@pytest.mark.parametrize("name", ["bend_obstacle_outside", "roundabout", "pass_slow_car", "junction_crossing_car"])
def test_copies_are_seeded_and_move_obstacles_within_bounds_in_the_routes_frame(name, tmp_path):
    sc = load_scenario(suite_dir() / f"{name}.toml")
    a = jittered_scene(name, 4, 1.0, tmp_path / "a")
    b = jittered_scene(name, 4, 1.0, tmp_path / "b")
    c = jittered_scene(name, 5, 1.0, tmp_path / "c")
    assert a.read_text() == b.read_text() and a.read_text() != c.read_text()
    copy = load_scenario(a)
    f = copy.v_desired / sc.v_desired
    assert 0.85 - 1e-3 <= f <= 1.15 + 1e-3
    for o, p in zip(sc.obstacles, copy.obstacles):
        before, after = sc.path.project(o.center[:2]), sc.path.project(p.center[:2])
        if abs(before.lateral) > 6.0:          # off the road (the roundabout's island: every s is as near)
            continue
        moving = bool(np.any(o.velocity))
        along, across = (3.0, 0.3) if moving else (2.0, 0.4)
        assert abs(after.s - before.s) <= along + 1e-2 and abs(after.lateral - before.lateral) <= across + 1e-2
        if moving:
            ratio = np.linalg.norm(p.velocity) / np.linalg.norm(o.velocity)
            assert 0.8 - 1e-3 <= ratio <= 1.2 + 1e-3


def test_the_bench_runs_a_copy_and_writes_what_it_printed(tmp_path, capsys):
    summary = bench_jitter(tmp_path, n=1, only=("oncoming_car",))
    out = capsys.readouterr().out
    doc = json.loads((tmp_path / "bench_jitter.json").read_text())
    (run,) = doc["runs"]
    assert run["scene"] == "oncoming_car" and run["outcome"] in out
    assert summary["runs"] == 1 and summary["completed_without_collision"] == (run["outcome"] == "completed"
                                                                                and run["collisions"] == 0)
    assert (tmp_path / "bench_jitter.png").stat().st_size > 0 and load_scenario(run["file"]).name == "oncoming_car-0"
