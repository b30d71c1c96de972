"""Core's loops compiled with numba (``njit``), for the controllers that run them.

Core stays pure (numpy and scipy only, no files): it writes a loop as plain Python
(``vflpcd.core.control.ebrhrl_kernel.solve_loop``, ``vflpcd.core.control.scheduled_kernel.problem_loop``,
``vflpcd.core.control.tick_kernel``'s ``window_loop``, ``window_lift_loop`` and ``linearisation_loop``,
``vflpcd.core.dynamics.encoder_kernel.encoder_loop``,
``vflpcd.core.dynamics.gp_kernel``'s ``add_sample_loop``, ``corrected_next_loop`` and ``ald_delta_loop``,
``vflpcd.core.path_kernel``'s ``nearest_arc_length`` and ``polyline_nearest``, the safety supervisor's
``vflpcd.core.safety.clearance_kernel``'s ``clearances_loop`` and ``within_reach_loop`` and
``vflpcd.core.safety.arc_kernel.arcs_loop``,
and the guidance's ``active_set_kernel.solve_loop``, ``integrate_kernel.step_loop``,
``path_grid_kernel.fill_loop`` and ``half_plane_kernel``'s ``half_planes_loop`` and ``clear_loop``) and takes the compiled function as an argument. This
module compiles each once per process, with numba's on-disk cache (beside the source, or numba's
user-wide cache where that is read-only, or ``$NUMBA_CACHE_DIR``; the systemd unit sets it), so a
later process loads it in milliseconds; with no writable place it compiles in memory at every
start. Each cache entry is named after the project files the loop is built from
(``loop_cache.cache_named``), so that a change to a function it calls, in another file, compiles it
anew. Without numba every ``*_loop()`` and ``guidance_loops()`` return None and their users run
their numpy paths (the guidance's steps run their loop interpreted).
"""

from __future__ import annotations

import logging
from functools import lru_cache

from vflpcd.controllers.loop_cache import cache_named

log = logging.getLogger(__name__)


@lru_cache(maxsize=1)
def ebrhrl_loop():
    """``ebrhrl_kernel.solve_loop`` compiled and loaded (``_warm_ebrhrl``), or None without numba."""
    from vflpcd.core.control.ebrhrl_kernel import solve_loop

    return _compiled("ebrhrl", solve_loop, _warm_ebrhrl)


@lru_cache(maxsize=1)
def scheduled_problem_loop():
    """``scheduled_kernel.problem_loop`` (the horizon of a model with a scheduled input matrix) compiled
    and loaded (``_warm_scheduled``), or None without numba."""
    from vflpcd.core.control.scheduled_kernel import problem_loop

    _algebra()
    return _compiled("scheduled_problem", problem_loop, _warm_scheduled)


@lru_cache(maxsize=1)
def tick_loops():
    """The tick's loops (``error_model.TickLoops``: the window and its lift, the nominal linearisation,
    the GP's correction, the increment fill, the command clip, the reference rows, the horizon in one
    call, a threat's safety points) compiled and loaded (``_warm_tick_*``), or None without numba."""
    from vflpcd.core.control.barrier_kernel import safety_points_loop
    from vflpcd.core.control.error_model import TickLoops
    from vflpcd.core.control.horizon_reference import strided_rows
    from vflpcd.core.control.rate_kernel import increment_loop
    from vflpcd.core.control.tick_kernel import command_loop, linearisation_loop, window_lift_loop, window_loop
    from vflpcd.core.control.horizon_kernel import horizon_command_loop
    from vflpcd.core.dynamics.gp_kernel import corrected_next_loop

    _algebra()
    window = _compiled("tick_window", window_loop, _warm_tick_window)
    if window is None:
        return None
    _horizon_steps()
    _lift_steps()
    return TickLoops(window=window,
                     lift=_compiled("tick_lift", window_lift_loop, _warm_tick_lift, numpy_errors=True),
                     barrier=_compiled("tick_barrier", safety_points_loop, _warm_tick_barrier),
                     linearisation=_compiled("tick_linearisation", linearisation_loop, _warm_tick_linearisation),
                     correction=_compiled("tick_gp_correction", corrected_next_loop, _warm_tick_correction),
                     increment=_compiled("tick_increment", increment_loop, _warm_tick_increment),
                     command=_compiled("tick_command", command_loop, _warm_tick_command),
                     reference=_compiled("tick_reference", strided_rows, _warm_tick_reference),
                     horizon=_compiled("tick_horizon", horizon_command_loop, _warm_tick_horizon))


@lru_cache(maxsize=1)
def encoder_loop():
    """``encoder_kernel.encoder_loop`` (the deep Koopman encoder, ``KoopmanModel.compile_encoder``)
    compiled and loaded (``_warm_encoder``), or None without numba."""
    from vflpcd.core.dynamics.encoder_kernel import encoder_loop as loop

    _lift_steps()
    return _compiled("encoder", loop, _warm_encoder, numpy_errors=True)


@lru_cache(maxsize=1)
def gp_add_loop():
    """``gp_kernel.add_sample_loop`` (the online GP's per-sample update) compiled and loaded
    (``_warm_gp_add``), or None without numba."""
    from vflpcd.core.dynamics.gp_kernel import add_sample_loop

    _algebra()
    return _compiled("gp_add", add_sample_loop, _warm_gp_add)


@lru_cache(maxsize=1)
def ald_loop():
    """``gp_kernel.ald_delta_loop`` (the online GP dictionary's test of a sample) compiled and loaded
    (``_warm_ald``), or None without numba."""
    from vflpcd.core.dynamics.gp_kernel import ald_delta_loop

    _algebra()
    return _compiled("gp_ald", ald_delta_loop, _warm_ald)


@lru_cache(maxsize=1)
def path_loop():
    """``path_kernel.nearest_arc_length`` compiled and loaded (``_warm_path``), or None without numba."""
    from vflpcd.core.path_kernel import nearest_arc_length

    _path_window()
    return _compiled("path", nearest_arc_length, _warm_path)


@lru_cache(maxsize=1)
def polyline_loop():
    """``path_kernel.polyline_nearest`` (the plan monitor's nearest segment) compiled and loaded
    (``_warm_polyline``), or None without numba."""
    from vflpcd.core.path_kernel import polyline_nearest

    return _compiled("polyline", polyline_nearest, _warm_polyline)


@lru_cache(maxsize=1)
def supervisor_loops():
    """The safety supervisor's loops (``clearance_kernel``'s clearance test and its pre-filter,
    ``arc_kernel``'s manoeuvre) compiled and loaded (``_warm_clearances``, ``_warm_within_reach``,
    ``_warm_arcs``), as ``SupervisorLoops``, or None without numba."""
    from vflpcd.core.safety import arc_kernel, clearance_kernel
    from vflpcd.core.safety.supervisor import SupervisorLoops

    if not _jitable(clearance_kernel._box_distance, clearance_kernel._signed_distance, arc_kernel.arc_point,
                    arc_kernel._time_at):
        return None
    return SupervisorLoops(
        clearances=_compiled("clearances", clearance_kernel.clearances_loop, _warm_clearances),
        within_reach=_compiled("within_reach", clearance_kernel.within_reach_loop, _warm_within_reach),
        arcs=_compiled("arcs", arc_kernel.arcs_loop, _warm_arcs))


@lru_cache(maxsize=1)
def active_set_loop():
    """``active_set_kernel.solve_loop`` (the guidance fairing's and tight path's convex problems)
    compiled and loaded (``_warm_active_set``), or None without numba."""
    from vflpcd.core.guidance.active_set_kernel import solve_loop

    _scalars()
    return _compiled("active_set", solve_loop, _warm_active_set)


@lru_cache(maxsize=1)
def integrate_loop():
    """``integrate_kernel.step_loop`` (the guidance's steps of eq. (xi_r)) compiled and loaded
    (``_warm_integrate``), or None without numba."""
    from vflpcd.core.guidance.integrate_kernel import step_loop

    _scalars()
    return _compiled("integrate", step_loop, _warm_integrate)


@lru_cache(maxsize=1)
def half_planes_loop():
    """``half_plane_kernel.half_planes_loop`` (the fairing's half-planes) compiled and loaded
    (``_warm_half_planes``), or None without numba."""
    from vflpcd.core.guidance.half_plane_kernel import half_planes_loop as loop

    _scalars()
    return _compiled("half_planes", loop, _warm_half_planes)


@lru_cache(maxsize=1)
def path_fill_loop():
    """``path_grid_kernel.fill_loop`` (the path's chi_P^ on a block of the guidance's grid) compiled
    and loaded (``_warm_path_fill``), or None without numba."""
    from vflpcd.core.guidance.path_grid_kernel import fill_loop

    _scalars()
    return _compiled("path_fill", fill_loop, _warm_path_fill)


@lru_cache(maxsize=1)
def clear_loop():
    """``half_plane_kernel.clear_loop`` (the fairing's clear check) compiled and loaded
    (``_warm_clear``), or None without numba."""
    from vflpcd.core.guidance.half_plane_kernel import clear_loop as loop

    _scalars()
    return _compiled("clear", loop, _warm_clear)


@lru_cache(maxsize=1)
def integrate3d_loop():
    """``integrate3d_kernel.steps3d_loop`` (the 3-D guidance's steps of eq. (xi_r)) compiled and
    loaded (``_warm_integrate3d``), or None without numba."""
    from vflpcd.core.guidance.integrate3d_kernel import steps3d_loop

    _scalars()
    return _compiled("integrate3d", steps3d_loop, _warm_integrate3d)


@lru_cache(maxsize=1)
def guidance_loops():
    """The guidance planner's loops compiled and loaded (``GuidanceLoops``), or None without numba."""
    from vflpcd.core.guidance.planner import GuidanceLoops

    active_set = active_set_loop()
    if active_set is None:
        return None
    return GuidanceLoops(active_set=active_set, steps=integrate_loop(), half_planes=half_planes_loop(),
                         steps3d=integrate3d_loop(), clear=clear_loop(), path_fill=path_fill_loop())


def compile_all() -> dict[str, bool]:
    """Compile (or load) every loop of this module now: name -> whether it is compiled (False:
    numba is missing and its numpy path runs). ``vflpcd compile`` calls it at installation, so
    that later processes load them from the cache in milliseconds instead of compiling for
    10-15 s of CPU (docs/results.md, "The test suite", for what compiling beside real-time runs did)."""
    return {fn.__name__: fn() is not None
            for fn in (ebrhrl_loop, scheduled_problem_loop, tick_loops, encoder_loop, gp_add_loop, ald_loop, path_loop,
                       polyline_loop, supervisor_loops, guidance_loops)}


@lru_cache(maxsize=1)
def _algebra() -> bool:
    """Register ``loop_algebra``'s functions, which the tick's, the GP's and the scheduled model's
    loops call, with numba; False without numba."""
    from vflpcd.core.loop_algebra import matvec, row_sq_distance

    return _jitable(matvec, row_sq_distance)


@lru_cache(maxsize=1)
def _horizon_steps() -> bool:
    """Register the loops that ``horizon_kernel.horizon_command_loop`` calls in turn (the tick's
    linearisation, GP correction, increment fill and command, Eb-RHRL's iterations) with numba, so
    that they compile into it; False without numba."""
    from vflpcd.core.control.ebrhrl_kernel import solve_loop
    from vflpcd.core.control.rate_kernel import increment_loop
    from vflpcd.core.control.tick_kernel import command_loop, linearisation_loop
    from vflpcd.core.dynamics.gp_kernel import corrected_next_loop

    return _jitable(linearisation_loop, corrected_next_loop, increment_loop, solve_loop, command_loop)


@lru_cache(maxsize=1)
def _lift_steps() -> bool:
    """Register what ``tick_kernel.window_lift_loop`` calls (``window_loop``, ``encoder_kernel``'s
    ``encoder_loop`` and its ``tanh_ratio``) with numba; False without numba."""
    from vflpcd.core.control.tick_kernel import window_loop
    from vflpcd.core.dynamics.encoder_kernel import encoder_loop, tanh_ratio

    return _jitable(window_loop, encoder_loop, tanh_ratio)


@lru_cache(maxsize=1)
def _path_window() -> bool:
    """Register ``path_kernel.window_runs``, which the path projection's loop calls, with numba;
    False without numba."""
    from vflpcd.core.path_kernel import window_runs

    return _jitable(window_runs)


@lru_cache(maxsize=1)
def _scalars() -> bool:
    """Register the scalar functions that the guidance's loops call (``primitives``',
    ``integrate_kernel.step_time`` and ``active_set_kernel``'s ``dual_step``, ``half_plane_gap``,
    ``normal_dot``) with numba, so that they compile with the loops; False without numba."""
    from vflpcd.core.guidance.active_set_kernel import dual_step, half_plane_gap, normal_dot
    from vflpcd.core.guidance.integrate3d_kernel import _repulsive_unit, _unit3, piece_at
    from vflpcd.core.guidance.integrate_kernel import step_time
    from vflpcd.core.guidance.primitives import (cup_at, guiding_at, knot_interval, row_centre, superellipse_at,
                                                 superellipsoid_at)

    return _jitable(superellipse_at, row_centre, step_time, cup_at, guiding_at, dual_step, half_plane_gap,
                    normal_dot, superellipsoid_at, piece_at, knot_interval, _repulsive_unit, _unit3)


def _jitable(*fns) -> bool:
    """Register plain functions that compiled loops call with numba (``register_jitable``), once per
    process (the callers are cached); False without numba."""
    try:
        from numba.extending import register_jitable
    except ImportError:
        return False
    for fn in fns:
        register_jitable(fn)
    return True


def _compiled(name: str, fn, warm, numpy_errors: bool = False):
    """fn compiled with numba's cache (in memory where none can be written) and warmed, or None
    without numba (the caller's numpy path). ``numpy_errors``: a division by zero gives inf or NaN as
    in numpy instead of raising (numba's ``error_model="numpy"``), for a loop whose divisors are never
    zero, where the check would keep its loops from being vectorised."""
    try:
        from numba import njit
    except ImportError:
        log.info("event=loop_interpreted loop=%s reason=numba is not installed (numpy path)", name)
        return None
    errors = "numpy" if numpy_errors else "python"
    fn = cache_named(fn)             # its cache entry named after the project files it is built from
    try:
        loop = njit(cache=True, error_model=errors)(fn)
    except RuntimeError as exc:          # no writable cache location (numba's "no locator available")
        log.warning("event=loop_cache_unavailable loop=%s reason=%s (compiling in memory; set NUMBA_CACHE_DIR)",
                    name, exc)
        loop = njit(cache=False, error_model=errors)(fn)
    warm(loop)
    return loop


def _warm_ebrhrl(loop) -> None:
    """Compile (or load) the loop now, for the argument types EbRHRL passes, so that a controller's
    first tick does not pay for it (a daemon's first deadline)."""
    import numpy as np

    z = np.zeros
    loop(z((1, 1, 1)), z((1, 1, 1)), z((1, 1)), z(1), z((1, 1, 1)), z((1, 1)), z((1, 1)), z((1, 1)), z((1, 1, 1)),
         1.0, z((1, 1, 1)), z((2, 1, 1)), z(1), z((1, 1)), z(1), z(1, np.int64), z((2, 1)), z((0, 2, 1)),
         z((0, 2, 1)), z(0), 1.0, 1.0, 1, 1e-8, 1e-2, False, z((1, 1)), z((1, 1)))


def _warm_scheduled(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``ErrorModel._scheduled_linearisation`` passes."""
    import numpy as np

    loop(np.ones((2, 3)), np.eye(3), np.ones((3, 1)), np.zeros((3, 1)), 0, 1, -np.ones(1), np.ones(1))


def _warm_tick_window(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``ErrorModel.frame`` passes."""
    import numpy as np

    loop(np.zeros(3), np.zeros((1, 3)), 2, np.array([0, 1]), 2, np.zeros(3), np.ones(3), np.zeros((2, 3)),
         np.zeros((2, 3), np.float32))


def _warm_encoder(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``KoopmanModel.encode`` passes."""
    import numpy as np

    loop(np.zeros((2, 3), np.float32), np.zeros(6, np.float32), np.zeros(2, np.float32), np.array([3, 2]),
         np.zeros((2, 2, 3), np.float32), np.zeros((2, 2)), 0)


def _warm_tick_lift(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``ErrorModel.frame`` passes with a deep
    Koopman lift (``BufferedLift.encoder``)."""
    import numpy as np

    loop(np.zeros(3), np.zeros((1, 3)), 2, np.array([0, 1]), 2, np.zeros(3), np.ones(3), np.zeros((2, 3)),
         np.zeros((2, 3), np.float32), np.zeros(6, np.float32), np.zeros(2, np.float32), np.array([3, 2]),
         np.zeros((2, 2, 3), np.float32), np.zeros((2, 6)))


def _warm_tick_barrier(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``ErrorModel.safety_points_in_window``
    passes (a quadrotor's 3-D positions are arrays of the same types as a car's 2-D ones)."""
    import numpy as np

    z = np.zeros((2, 2))
    loop(1, np.ones(2), np.zeros(2), 0.0, np.zeros(2), 0.0, z, np.zeros(2), 0.5, 2, np.arange(2), 2, np.zeros(6),
         z.copy(), z.copy())


def _warm_tick_linearisation(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``ErrorModel._linearisation`` passes."""
    import numpy as np

    loop(np.ones((2, 3)), np.eye(3), np.ones((3, 1)), np.ones((1, 1)), 1, -np.ones(1), np.ones(1))


def _warm_tick_increment(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``RateForm.increments`` passes: the error
    model's c (a view of its next states' columns), its nominal B (read-only, broadcast along the
    horizon) or a scheduled model's (contiguous), and the limits' read-only du_max."""
    import numpy as np

    c = np.zeros((2, 3))[:, :2]
    for B in (np.broadcast_to(np.ones((2, 1)), (2, 2, 1)), np.ones((2, 2, 1))):
        loop(c, B, np.zeros((2, 1)), np.zeros(2), np.zeros(1), np.ones(1), np.zeros(1, np.int64), np.zeros((2, 3)),
             np.zeros(3), np.zeros((2, 1)), np.zeros((2, 1)))


def _warm_tick_command(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``tick_horizon.clipped_command`` passes."""
    import numpy as np

    loop(np.zeros(1), np.zeros(1), -np.ones(1), np.ones(1), np.zeros(1), np.ones(1))


def _warm_tick_horizon(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``CompiledHorizon.solve`` passes (one
    compiled form with a GP and without: ``tick_horizon.no_gp_arguments``), on a model of two
    observables, one input and one step (the nominal B broadcast along two)."""
    import numpy as np

    from vflpcd.core.control.tick_horizon import no_gp_arguments
    from vflpcd.core.dynamics.compensation import KoopmanCompensation

    z = np.zeros
    comp = KoopmanCompensation(np.eye(2), np.ones((2, 1)), np.ones((2, 1)), [0])
    for gp in (no_gp_arguments(comp.n_z, 2), (True, *comp.mean_arguments(_tiny_gp()))):
        loop(z(2), z((2, 2)), np.eye(2), z((2, 1)), np.ones((1, 1)), 1, -np.ones(1), np.ones(1), z(1), np.ones(1),
             *gp, True, np.broadcast_to(np.ones((1, 1)), (2, 1, 1)), z(1, np.int64), z((1, 2)), z(2), z((1, 1)),
             z((1, 1)), z((1, 2, 2)), z((1, 2, 1)), z((1, 1, 2)), np.eye(2), np.ones((1, 1)), np.eye(2),
             np.ones((1, 1, 1)), 1.0, z((1, 1, 1)), z((2, 1, 2)), z(1), z((1, 2)), z(2), z(1, np.int64), z((2, 1)),
             z((0, 2, 1)), z((0, 2, 1)), z(0), 1.0, 1.0, 1, 1e-8, 1e-2, False)


def _warm_tick_reference(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``HorizonReference.at`` passes."""
    import numpy as np

    for w in (0.0, 0.5):
        loop(np.zeros((4, 2)), 1, 1, w, np.empty((2, 2)))


def _tiny_gp():
    """A GP of one inducing input (two inputs, one output) built as the controller's are: its arrays
    read-only, a type of their own to numba (a loop warmed on writable ones compiled again at the
    first sample, and the daemon's loop stalled 0.5 s)."""
    import numpy as np

    from vflpcd.core.dynamics.sparse_gp import FITCGP, SEHyper

    one = np.ones(1)
    return FITCGP.fit(np.zeros((1, 2)), np.zeros((1, 2)), np.zeros((1, 1)), SEHyper(one, one, one))


def _warm_gp_add(loop) -> None:
    """Compile (or load) the loop now, through ``FITCGP.add_sample`` itself (``_tiny_gp``)."""
    import numpy as np

    _tiny_gp().add_sample(np.zeros(2), np.zeros(1), loop)


def _warm_tick_correction(loop) -> None:
    """Compile (or load) the loop now, through ``KoopmanCompensation.corrected_next`` itself (``_tiny_gp``)."""
    import numpy as np

    from vflpcd.core.dynamics.compensation import KoopmanCompensation

    comp = KoopmanCompensation(np.eye(2), np.ones((2, 1)), np.ones((2, 1)), [0])
    U = np.zeros((2, 2))
    comp.corrected_next(U[1:] @ comp.A.T, U[:-1], np.zeros((1, 1)), _tiny_gp(), loop)


def _warm_ald(loop) -> None:
    """Compile (or load) the loop now, through ``ALDDictionary.consider`` itself."""
    import numpy as np

    from vflpcd.core.dynamics.ald import ALDDictionary

    ald = ALDDictionary(2, 0.1, 4, delta_loop=loop)
    ald.consider(np.zeros(2))
    ald.consider(np.ones(2))


def _warm_polyline(loop) -> None:
    """Compile (or load) the loop now, for the arguments ``path.nearest_on_polyline`` passes (d = 2, 3)."""
    import numpy as np

    for d in (2, 3):
        loop(np.zeros(d), np.ones((3, d)))


def _warm_arcs(loop) -> None:
    """Compile (or load) the loop now, for the arguments ``GroundSupervisor._poses_moving`` passes."""
    import numpy as np

    loop(0.0, 0.0, 0.0, 0.0, 0.01, 0.0, 1.0, 0.5, 2, 1.0, 0.0, 0.1, 1.0, -1.0, 1.0, np.empty((4, 2)), np.empty(4),
         np.empty(4))


def _warm_within_reach(loop) -> None:
    """Compile (or load) the loop now, for the arguments ``Supervisor._within_reach`` passes (d = 2, 3)."""
    import numpy as np

    for d in (2, 3):
        loop(np.zeros(d), np.zeros((2, 2 * d + 1)), np.zeros((2, 4 + d)), 0.0, 1.0, 1.0, np.empty(2, dtype=bool))


def _warm_clearances(loop) -> None:
    """Compile (or load) the loop now, for the arguments ``Supervisor._compiled_clearances`` passes:
    the car's (d = 2) and the quadrotor's (d = 3)."""
    import numpy as np

    for d in (2, 3):
        motion = np.zeros((2, 2 * d + 1))
        motion[1, d] = 1.0
        shape = np.zeros((2, 4 + d))
        shape[:, 1] = 1.0
        shape[1, 3] = 1.0
        loop(np.zeros((3, d)), np.zeros(3), np.arange(3.0), np.zeros(2), motion, shape, np.ones((3, d)), True, True,
             False, 0.5, 2.0, 0.35)


def _warm_path(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``ReferencePath.arc_length_of`` passes."""
    import numpy as np

    loop(np.zeros(2), np.zeros((2, 2)), np.array([0.0, 1.0]), np.ones((1, 2)), np.ones(1), -1.0, 2.0, False, False)


def _warm_active_set(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``fairing.solve_active_set`` passes."""
    import numpy as np

    loop(np.eye(1, 4), np.zeros(4), np.zeros((2, 2)), np.zeros(2), np.zeros(2, bool), np.zeros(2, bool),
         np.zeros(4), 1, 1.0, 1e-6, 1e-13)


def _warm_integrate3d(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``GuidancePlanner3D._integrate`` passes."""
    import numpy as np

    z = np.zeros
    frame = np.concatenate([z(3), np.eye(3).ravel()])
    params = np.array([1.0, 3.0, 0.05, 0.05, 1e-3, 0.1, 1.0, 2.0, 0.0, 1.0, 0.0, 1.0, -0.3])
    loop(z(3), z((3, 3)), z((0, 20)), z(0), frame, np.array([0.0, 1.0]), z((4, 1, 4)), params, z(0), z(2, np.int64))


def _warm_integrate(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``grid.integrate`` passes."""
    import numpy as np

    z = np.zeros
    loop(z(7), z((2, 2)), z((1, 1, 2)), np.ones((1, 1), bool), np.array([0.0, 0.0, 1.0, 32.0]), z((0, 6)), z(0),
         z(0), z((0, 13)), z((0, 18)), z(0, np.int64), np.array([0.3, 0.2, 1.0, 1.0, 1e-3, 0.1, 1.0, 1.0, 0.0, 0.0,
         1.0, 0.0, 0.0, 1.0]), z(0), z(3, np.int64))


def _warm_path_fill(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``grid.PathGrid.fill`` passes."""
    import numpy as np

    loop(np.zeros(1), np.zeros(1), np.zeros(2), np.eye(2), np.array([0.0, 1.0]), np.zeros((4, 1)), -1.0, 1.0,
         np.zeros((1, 1, 2)))


def _warm_clear(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``fairing.compiled_clear`` passes."""
    import numpy as np

    loop(np.zeros((1, 2)), np.zeros(1), np.zeros((0, 12)), 0, 1, np.zeros(1, dtype=bool), 1.0)


def _warm_half_planes(loop) -> None:
    """Compile (or load) the loop now, for the argument types ``fairing.compiled_half_planes`` passes."""
    import numpy as np

    loop(np.zeros((1, 2)), np.zeros(1), np.zeros((0, 12)), 0.8, 6, 1e-10, np.zeros((1, 2)), np.zeros(1))
