"""The guidance's compiled loops give the numbers of their interpreted and numpy paths."""

from dataclasses import replace

import numpy as np
import pytest

from vflpcd.config.scenarios import default_guidance
from vflpcd.controllers.loops import clear_loop, guidance_loops, half_planes_loop, integrate_loop, path_fill_loop
from vflpcd.core.guidance.fairing import Region, compiled_clear, compiled_half_planes, half_planes, regions_clear
from vflpcd.core.guidance.grid import FieldGrid, integrate
from vflpcd.core.guidance.planner import GuidancePlanner, _value_grad_at_times, _within_reach
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.path import ReferencePath
from vflpcd.core.shapes import Box, Circle, Ellipse


def _obstacle(oid, shape, x, y, yaw=0.0, velocity=(0.0, 0.0), stamp=0.0):
    return ObstacleState(id=oid, shape=shape, center=np.array([x, y]), yaw=yaw, velocity=np.array(velocity),
                         stamp=stamp)


@pytest.fixture(scope="module")
def scene():
    """A bent path with a parked car (its auto virtual obstacle), a cone, a crossing walker and a
    car coming the other way: every kind of term the steps add."""
    path = ReferencePath.from_waypoints(np.array([[0.0, 0.0], [30.0, 0.0], [60.0, 8.0], [90.0, 20.0]]))
    planner = GuidancePlanner(path, replace(default_guidance(), virtual="auto"), 6.0, 3.0, 1.0, 0.05)
    prepared = planner.prepare(0.0, [_obstacle("car", Box(4.5, 1.9), 25.0, 0.4, 0.1),
                                     _obstacle("cone", Circle(0.3), 55.0, 6.0)])
    movers = [_obstacle("walker", Circle(0.4), 45.0, -6.0, velocity=(0.0, 1.4), stamp=1.0),
              _obstacle("oncoming", Ellipse(2.4, 1.0), 90.0, 26.0, 0.45, velocity=(-5.0, -2.4))]
    field = replace(prepared.field, movers=[planner.actual_term(planner.implicit(o), 0.0) for o in movers])
    assert field.statics and field.virtuals and len(field.movers) == 2
    return planner, prepared, field


@pytest.mark.parametrize("timed", [False, True])
def test_the_compiled_steps_are_the_interpreted_ones(scene, timed):
    """The same trajectory to 1e-12 m, the same gammas, virtual stop, inherited steps and end, with
    the movers placed by the default speed and by an earlier pass's step times."""
    planner, prepared, field = scene
    steps = 0.1 * np.arange(1500) / 5.0 if timed else None
    runs = [integrate(field, prepared.grid, np.zeros(2), prepared.x_end, 0.1, 1e-3, 3000, t0=0.0, speed=6.0,
                      heading=np.array([1.0, 0.0]), step_times=steps, loop=loop)
            for loop in (None, integrate_loop())]
    interpreted, compiled = runs
    assert interpreted.reached and len(interpreted.xy) > 500
    assert interpreted.xy.shape == compiled.xy.shape
    np.testing.assert_allclose(compiled.xy, interpreted.xy, rtol=0.0, atol=1e-12)
    assert compiled.gammas == interpreted.gammas and None not in compiled.gammas
    assert compiled.virtual_off == interpreted.virtual_off and compiled.virtual_off[0] is not None
    assert compiled.inherited == interpreted.inherited and compiled.reached


def test_the_compiled_path_grid_fill_is_the_numpy_one(scene):
    """Every block of the bent path's grid, which reaches past both ends of its spline (the linear
    continuation) and over every piece: the same chi_P^ to 1e-12, unit vectors."""
    planner, prepared, field = scene
    x0, x1, y0, y1 = prepared.grid.bounds
    ends = prepared.field.path.to_local(np.array([[x0, y0], [x1, y1]]))[:, 0]
    assert ends[0] < prepared.field.path.x0 and ends[1] > prepared.field.path.x1
    grids = [FieldGrid.build(prepared.field, prepared.grid.bounds, 0.1, fill).path for fill in (None, path_fill_loop())]
    for g in grids:
        for bi, row in enumerate(g.filled):
            for bj in range(len(row)):
                g.fill(bi, bj)
    numpy_fill, compiled = grids
    assert compiled.loop is not None and numpy_fill.loop is None and compiled.data.shape[0] * compiled.data.shape[1] > 1e5
    np.testing.assert_allclose(compiled.data, numpy_fill.data, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(compiled.data, axis=-1), 1.0, atol=1e-12)


def test_the_compiled_half_planes_are_the_numpy_ones(scene):
    """Points around the movers' and the statics' regions (some inside two at once): the same
    half-planes to 1e-12, and the same free points."""
    planner, prepared, field = scene
    terms = field.statics + field.movers
    rng = np.random.default_rng(3)
    t = rng.uniform(0.0, 12.0, 4000)
    which = rng.integers(len(terms), size=len(t))
    x = np.array([terms[i].implicit.center_at(tk) for i, tk in zip(which, t)]) + rng.normal(0.0, 2.5, (len(t), 2))
    regions = [Region(lambda p, tt, o=term.implicit: _value_grad_at_times(o, p, tt), term.implicit.c,
                      lambda p, tt, o=term.implicit: _within_reach(o, p, tt)) for term in terms]
    n, b = half_planes(x, t, regions)
    rows = np.array([term.implicit.row() for term in terms])
    n_c, b_c = compiled_half_planes(half_planes_loop(), rows, x, t)
    held = np.isfinite(b)
    assert held.sum() > 1000 and (~held).sum() > 100
    np.testing.assert_array_equal(np.isfinite(b_c), held)
    np.testing.assert_allclose(n_c, n, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(b_c[held], b[held], rtol=1e-12, atol=1e-12)       # b = n . q: q tens of metres


def test_the_compiled_clear_check_is_the_numpy_one(scene):
    """Paths of points around the regions, some through one, some eased there: the compiled check
    says clear exactly where ``regions_clear`` does, and the planner's ``reaches_any`` (compiled)
    exactly where ``_reaches`` does, at the repulsive level and beyond it (both sides seen)."""
    planner, prepared, field = scene
    terms = field.statics + field.movers
    regions = [Region(lambda p, tt, o=term.implicit: _value_grad_at_times(o, p, tt), term.implicit.c,
                      lambda p, tt, o=term.implicit: _within_reach(o, p, tt)) for term in terms]
    rows = np.array([term.implicit.row() for term in terms])
    compiled = GuidancePlanner(planner.path, planner.params, planner.v_desired, planner.a_lat_max,
                               planner.body_radius, planner.dt, loops=guidance_loops)
    assert planner._loops().clear is None and compiled._loops().clear is not None
    rng = np.random.default_rng(5)
    seen = set()
    for _ in range(300):
        i = rng.integers(len(terms))
        t = np.sort(rng.uniform(0.0, 12.0, 40))
        centre = terms[i].implicit.center_at(float(t[20]))
        x = centre + rng.normal(0.0, 1.0, 2) + np.linspace(-1.0, 1.0, 40)[:, None] * rng.normal(0.0, 4.0, 2)
        eased = rng.random(40) < 0.1
        clear = regions_clear(x, t, regions, eased)
        assert compiled_clear(clear_loop(), rows, x, t, eased) == clear
        seen.add(clear)
        for scale in (1.0, 1.25):               # the planner's checks (meets_mover's slack: 1.25)
            reaches = planner.reaches_any(terms, x, t, scale)
            assert compiled.reaches_any(terms, x, t, scale) == reaches
            seen.add(("reaches", scale, reaches))
    assert {True, False, ("reaches", 1.25, True), ("reaches", 1.25, False)} <= seen


def test_a_static_obstacle_without_a_direction_is_an_error_not_a_loop(scene):
    """gamma_i = 0 would leave the obstacle undecided at its first entry, and the steps would ask
    for it again and again: it is refused by name."""
    from vflpcd.core.guidance.implicit import GuidanceError

    planner, prepared, field = scene
    bad = replace(field, statics=[replace(field.statics[0], gamma=0.0)] + field.statics[1:], movers=[])
    with pytest.raises(GuidanceError, match="gamma must be"):
        integrate(bad, prepared.grid, np.zeros(2), prepared.x_end, 0.1, 1e-3, 3000, heading=np.array([1.0, 0.0]),
                  loop=integrate_loop())
