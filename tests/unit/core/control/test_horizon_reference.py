"""The horizon's reference read from the plan's table (``HorizonReference``): the same rows as a
linear interpolation of each column, on the plan's grid and off it, past its end, and for plans
whose times are not a grid of the horizon's step."""

import numpy as np
import pytest

from vflpcd.core.control.horizon_reference import HorizonReference

N, DT = 20, 0.05
STOPPED = np.array([False, False, True, True])


def _plan(h: float, t0: float = 3.2, rows: int = 150, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = t0 + h * np.arange(rows)
    cols = np.cumsum(rng.normal(size=(rows, 4)), axis=0)
    return t, cols


def _interp(t_plan, cols, t, standing):
    times = t + DT * np.arange(N + 1)
    return np.column_stack([np.interp(times, t_plan, cols[:, j], right=standing[j]) for j in range(cols.shape[1])])


@pytest.mark.parametrize("h", [DT, DT / 5, DT / 2])
def test_on_the_grid_and_off_it_the_rows_are_the_interpolation_of_each_column(h):
    t_plan, cols = _plan(h)
    ref = HorizonReference(t_plan, cols, STOPPED, DT, N)
    standing = np.where(STOPPED, 0.0, cols[-1])
    last = t_plan[-1] - N * DT
    for t in np.concatenate([t_plan[:-1][t_plan[:-1] <= last], np.linspace(t_plan[0], last, 37)]):
        np.testing.assert_allclose(ref.at(t), _interp(t_plan, cols, t, standing), rtol=0, atol=1e-12)


def test_before_the_plan_its_first_row_and_past_its_end_the_plan_stands():
    t_plan, cols = _plan(DT)
    ref = HorizonReference(t_plan, cols, STOPPED, DT, N)
    np.testing.assert_array_equal(ref.at(t_plan[0] - 1.0)[0], cols[0])
    past = ref.at(t_plan[-1] + 0.3)
    np.testing.assert_array_equal(past, np.broadcast_to(np.where(STOPPED, 0.0, cols[-1]), past.shape))
    ending = ref.at(t_plan[-1] - 5 * DT)            # the horizon runs past the end on the grid
    np.testing.assert_array_equal(ending[:6], cols[-6:])
    np.testing.assert_array_equal(ending[6:], np.broadcast_to(np.where(STOPPED, 0.0, cols[-1]), (N - 5, 4)))


@pytest.mark.parametrize("times", ["uneven", "not a divisor", "single"])
def test_times_that_are_not_a_grid_of_the_step_are_interpolated_per_column(times):
    t_plan, cols = _plan(DT)
    if times == "uneven":
        t_plan = t_plan + np.random.default_rng(1).uniform(0.0, 0.01, len(t_plan))
        t_plan.sort()
    elif times == "not a divisor":
        t_plan = t_plan[0] + 0.03 * np.arange(len(t_plan))
    else:
        t_plan, cols = t_plan[:1], cols[:1]
    ref = HorizonReference(t_plan, cols, STOPPED, DT, N)
    standing = np.where(STOPPED, 0.0, cols[-1])
    for t in (t_plan[0] - 0.1, t_plan[0] + 0.123, t_plan[-1] - 0.4, t_plan[-1] + 0.2):
        want = _interp(t_plan, cols, t, standing) if len(t_plan) > 1 else np.broadcast_to(
            np.where(t + DT * np.arange(N + 1)[:, None] > t_plan[0], standing, cols[0]), (N + 1, 4))
        np.testing.assert_allclose(ref.at(t), want, rtol=0, atol=1e-12)


def test_rows_and_times_must_match():
    with pytest.raises(ValueError, match="one row per time"):
        HorizonReference(np.arange(5.0), np.zeros((4, 2)), np.zeros(2, bool), DT, N)


@pytest.mark.parametrize("run", ["python", "compiled"])
@pytest.mark.parametrize("h", [DT, DT / 5])
def test_the_strided_rows_loop_gives_the_numpy_rows(run, h):
    """``strided_rows`` (run as Python and compiled) reads the same rows as the numpy path, exactly: on
    the plan's grid, off it, before the plan and past its end."""
    from vflpcd.core.control.horizon_reference import strided_rows

    loop = strided_rows
    if run == "compiled":
        from vflpcd.controllers.loops import tick_loops

        loops = tick_loops()
        if loops is None:
            pytest.skip("numba is not installed")
        loop = loops.reference
    t_plan, cols = _plan(h, seed=3)
    plain = HorizonReference(t_plan, cols, STOPPED, DT, N)
    fast = HorizonReference(t_plan, cols, STOPPED, DT, N, loop)
    times = np.concatenate([t_plan[::7], np.linspace(t_plan[0] - 1.0, t_plan[-1] + 1.0, 53)])
    for t in times:
        np.testing.assert_array_equal(fast.at(t), plain.at(t))
