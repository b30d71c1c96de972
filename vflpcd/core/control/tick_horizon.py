"""A tick's horizon for ``VFLPC``: its problem, the solves of it and the command, two ways.

``VFLPC.step`` lifts the window (``ErrorModel.frame``), then asks a horizon for a solve in a mode
(a rate form and its solver, bounded or not; the light weights may be tried before the heavy ones)
and for the command of the solve it keeps (or of the plan it falls back on):

* ``ProblemHorizon`` builds the ``HorizonProblem`` call by call (``ErrorModel.problem``), its
  increment form per rate form (``RateForm.increments``), and solves with the solver's ``solve``:
  any solver, the numpy paths, every model;
* ``CompiledHorizon`` does the problem, its increment form, Eb-RHRL's iterations and the clipped
  command in one compiled call per solve (``horizon_kernel.horizon_command_loop``), with the same
  numbers: where the tick's loops are compiled, for Eb-RHRL and a model whose linearisation is the
  nominal pair (not scheduled, without the GP's Jacobians). What the call did not compute (a
  held plan's command, the terminal law's start after a failed solve) is built call by call.

Both: ``begin(frame, u_prev, gp)`` at a tick, then ``solve(rate, solver, barrier, bounded)`` ->
(u~ or v (N, n_u), SolveInfo) (rate None: the problem itself), ``start(rate)`` (the start the
terminal law acts on) and ``command(rate, v0)`` (u = u_r,0 + u~_0 clipped into the limits,
u~_0 = ``rate.deviation`` of v0 in an increment form).
"""

from __future__ import annotations

import numpy as np

from vflpcd.core.control.ebrhrl import EbRHRL
from vflpcd.core.control.error_model import ErrorModel, Limits, TickFrame
from vflpcd.core.control.problem import HorizonProblem


def clipped_command(limits: Limits, u_ref0: np.ndarray, u_tilde0: np.ndarray, u_prev: np.ndarray,
                    loop=None) -> np.ndarray:
    """u = u_r,0 + u~_0 within the magnitude limits, then within the rate limit of u_prev
    (``loop``: ``tick_kernel.command_loop`` compiled, the same numbers)."""
    if loop is not None:
        return loop(u_ref0, u_tilde0, limits.u_min, limits.u_max, u_prev, limits.du_max)
    u = np.minimum(np.maximum(u_ref0 + u_tilde0, limits.u_min), limits.u_max)             # magnitude limits
    return np.minimum(np.maximum(u, u_prev - limits.du_max), u_prev + limits.du_max)     # rate limits


def no_gp_arguments(n_z: int, n_K: int) -> tuple:
    """``horizon_command_loop``'s GP arguments (``corrected`` to B_d) for a tick without a GP: not
    corrected, and arrays of the types a GP's have (``KoopmanCompensation.mean_arguments``: its
    inducing inputs, sf2 and alpha read-only), so the loop has one compiled form for both."""
    arrays = np.zeros((1, n_z)), np.ones(1), np.zeros((1, 1)), np.zeros((1, 1)), np.zeros((n_K, 1))
    for a in (arrays[0], arrays[1], arrays[3]):
        a.flags.writeable = False
    return (False, np.zeros(1, np.int64), *arrays)


class ProblemHorizon:
    """The horizon built call by call (module docstring); ``problem``: the tick's ``HorizonProblem``."""

    def __init__(self, errors: ErrorModel, command_loop=None) -> None:
        self.errors, self._command_loop = errors, command_loop
        self.problem: HorizonProblem | None = None
        self._forms: list = []          # [(rate form, (its increment problem, bounds))] of this tick

    def begin(self, frame: TickFrame, u_prev: np.ndarray, gp) -> "ProblemHorizon":
        self.problem = self.errors.problem(frame, u_prev, gp)
        self._forms.clear()
        return self

    def _form(self, rate) -> tuple[HorizonProblem, tuple[np.ndarray, np.ndarray] | None]:
        if rate is None:
            return self.problem, None
        for r, form in self._forms:
            if r is rate:
                return form
        form = rate.increments(self.problem)
        self._forms.append((rate, form))
        return form

    def solve(self, rate, solver, barrier, bounded: bool = False):
        problem, bounds = self._form(rate)
        return solver.solve(problem, barrier, bounds) if bounded else solver.solve(problem, barrier)

    def start(self, rate) -> np.ndarray:
        return self._form(rate)[0].x0

    def command(self, rate, v0: np.ndarray) -> np.ndarray:
        u_tilde0 = v0 if rate is None else rate.deviation(self.start(rate), v0)
        return clipped_command(self.errors.limits, self.problem.u_ref[0], u_tilde0, self.problem.u_prev,
                               self._command_loop)


class CompiledHorizon:
    """The horizon in one compiled call per solve (module docstring), by the error model's
    ``tick_loops`` (``horizon``: ``horizon_kernel.horizon_command_loop``; ``command``:
    ``tick_kernel.command_loop``, for the commands the call did not make)."""

    def __init__(self, errors: ErrorModel) -> None:
        m, lim, loops = errors.model, errors.limits, errors.tick_loops
        self.errors, self.loop, command_loop = errors, loops.horizon, loops.command
        self._calls = ProblemHorizon(errors, command_loop)
        self._model = (m.A, m.B, errors.B_x_pinv, m.n_x, lim.u_min, lim.u_max)
        n, n_u, N = errors.n, m.n_u, errors.N
        self._no_gp = no_gp_arguments(errors.comp.n_z if errors.comp is not None else 1, m.n_K)
        self._B_plain = np.ascontiguousarray(errors.B_N)       # the solver's B without an increment form
        self._plain = (False, errors.B_N, np.zeros(0, np.int64), np.zeros((N, n + n_u)), np.zeros(n),
                       np.zeros((N, n_u)), np.zeros((N, n_u)))     # no increment form: its arrays unused
        self._frame: TickFrame | None = None
        self._u_prev = self._gp = self._gp_model = self._u = self._target = None
        self._begun = False

    @staticmethod
    def applies(errors: ErrorModel) -> bool:
        """Whether the compiled call computes what ``ProblemHorizon`` would for this error model
        (module docstring; a solver other than a compiled Eb-RHRL is asked through ``ProblemHorizon``)."""
        loops = errors.tick_loops
        return (loops is not None and loops.horizon is not None and loops.command is not None
                and loops.increment is not None and not errors.model.scheduled and not errors.gp_jacobians)

    def begin(self, frame: TickFrame, u_prev: np.ndarray, gp) -> "CompiledHorizon":
        self._frame, self._u_prev = frame, np.asarray(u_prev, float)
        comp = self.errors.comp
        self._gp_model = gp if comp is not None else None
        self._gp = (True, *comp.mean_arguments(gp)) if self._gp_model is not None else self._no_gp
        self._u = self._target = None
        self._begun = False
        return self

    def solve(self, rate, solver, barrier, bounded: bool = False):
        if not (isinstance(solver, EbRHRL) and solver.compiled):      # another solver: its own solve
            return self._problem().solve(rate, solver, barrier, bounded)
        e = self.errors
        if rate is not None:
            w = rate.work(e.N)
            A, B = rate.augmented(e.A_N, e.B_N)
            form, A_cl = (True, e.B_N, w.commanded, w.c, w.x0, w.lo, w.hi), solver.closed_loop_of(A, B)
        else:               # A - B K of the arrays ProblemHorizon's problem has (the same numbers)
            B, form, A_cl = self._B_plain, self._plain, solver.closed_loop_of(e.A_N, e.B_N)
        frame = self._frame
        u, target, iterations, eps_a, eps_c, saturated = self.loop(
            frame.U, frame.U_r, *self._model, self._u_prev, e.limits.du_max, *self._gp, *form, A_cl, B,
            *solver.loop_arguments(barrier), bounded)
        self._u, self._target = u, target
        return target, solver.loop_info(iterations, eps_a, eps_c, saturated)

    def start(self, rate) -> np.ndarray:
        return self._problem().start(rate)

    def command(self, rate, v0: np.ndarray) -> np.ndarray:
        """The call's own command when v0 is the first row of its last solve's targets, else built."""
        if self._target is not None and v0.base is self._target:
            return self._u
        return self._problem().command(rate, v0)

    def _problem(self) -> ProblemHorizon:
        if not self._begun:
            self._calls.begin(self._frame, self._u_prev, self._gp_model)
            self._begun = True
        return self._calls
