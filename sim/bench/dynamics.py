"""`vflpcd bench dynamics`: costs of the learned model and the online compensation demo.

Timings (median over repeated calls, single-threaded BLAS): encoder + lift of one state; the
FITC GP mean + Jacobian at one point, and a full refit (hyper-parameters + posterior), at the sizes
vflpc_ml ships (config/controllers/vflpc.toml [compensation]: inducing points, samples, channels).

Online compensation (paper section "Model Uncertainties Learning"): on ``racing_track``, the
nominal model (a ``LiftedLinearModel``, by default the shipped vehicle model) meets the plant
with the paper's "exact" parameters and process noise, driven by pure pursuit. Transitions of
the first 100 m feed an ``OnlineCompensator`` (ALD dictionary, FITC GP on the residual
d = B_d^+ (Upsilon_{k+1} - A Upsilon_k - B u_k) of the channels vflpc_ml ships: Y, psi, v_x, v_y, omega);
after one refit, the rest of the lap measures the one-step and 1-s open-loop prediction errors
of the nominal and the compensated model, in each prediction's own window frame (the 1-s
rollout re-lifts the predicted state at every step, Upsilon = [x, rho_e(x)]). It runs twice:
with the GP input [v_x, v_y, omega, u], and with the paper's [v_x, v_y, omega, rho_e, u] (the
paper's structure; the pose channels never enter the input, a sample's pose being its window
frame's origin). The GP works in
lifted coordinates scaled by their spread on the first 100 m (a linear change of variables, so
that one isotropic length scale fits inputs of different units).

Steering response: from straight driving at speeds of 1.5 to 15 m/s, the steering angle held at
+-delta for 2 s (a_x = 0), the yaw rate that the model predicts (open loop, the horizon's own
prediction) against the plant's (nominal parameters). The model is linear in the input
(Upsilon_{k+1} = A Upsilon_k + B u_k), so its steady yaw-rate gain per radian of steering is the
same at every speed, while the car's grows with speed (kinematic at low speed, understeering at
high speed): the ratio says where the horizon's model over- or under-estimates the steering.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from vflpcd.controllers import make_controller
from vflpcd.controllers.vflpc import load_params
from sim.runner import run_closed_loop
from vflpcd.config.scenarios import load_scenario
from vflpcd.core.dynamics.compensation import KoopmanCompensation, OnlineCompensator, channel_rows
from vflpcd.core.dynamics.lifted import LiftedLinearModel, to_window_frame
from vflpcd.core.dynamics.sparse_gp import FITCGP, SEHyper, refit
from vflpcd.config.vehicles import STATE_NAMES, BicycleConfig
from sim.plants.dynamic_bicycle import DynamicBicycle

SHIPPED = load_params("ground")      # the GP that vflpc_ml ships with ([compensation] of vflpc.toml)


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        fn()
        times.append(time.perf_counter_ns() - t0)
    return float(np.median(times)) * 1e-9


def timings(model: LiftedLinearModel, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    x = np.zeros(model.n_x)
    x[model.state_names.index("vx")] = 6.0
    t_lift = _median_time(lambda: model.lift(x), 2000)
    n_z, n_y, m, n = 8, len(SHIPPED.gp_channels), SHIPPED.gp_m_max, SHIPPED.gp_n_max
    Z = rng.normal(size=(n, n_z))
    Y = np.column_stack([np.sin(Z[:, j % n_z]) + 0.1 * Z[:, (j + 1) % n_z] for j in range(n_y)])
    Zm = Z[rng.choice(n, m, replace=False)]
    hyp = SEHyper(sf2=np.ones(n_y), ell=np.full(n_y, 2.0), sn2=np.full(n_y, 1e-2))
    gp = FITCGP.fit(Zm, Z, Y, hyp)
    z = rng.normal(size=n_z)
    for _ in range(200):
        gp.mean_jacobian(z)
    t_gp = _median_time(lambda: gp.mean_jacobian(z), 2000)
    t_refit = _median_time(lambda: refit(None, Zm, Z, Y, hyp), 5)
    return {"lift_s": t_lift, "gp_mean_jacobian_s": t_gp, "gp_refit_s": t_refit,
            "gp_inducing": m, "gp_samples": n, "gp_outputs": n_y}


def compensation_demo(model: LiftedLinearModel, seed: int = 0, learn_m: float = 100.0,
                      horizon_s: float = 1.0, with_encoder: bool = False) -> dict:
    """One lap of racing_track on the mismatched plant; see the module docstring. Returns the errors."""
    scenario = load_scenario("racing_track")
    scenario = replace(scenario, params="exact", process_noise=True)
    record = run_closed_loop(scenario, make_controller("pure_pursuit", scenario), seed=seed)
    names = record.state_names
    if tuple(names) != tuple(model.state_names) or tuple(record.control_names) != tuple(model.control_names):
        raise ValueError(f"model layout {model.state_names}/{model.control_names} does not match the plant's "
                         f"{names}/{record.control_names}")
    ok = np.all(np.isfinite(record.applied), axis=1)
    X, u = record.state[ok], record.applied[ok]
    n_x = model.n_x
    pairs = np.array([to_window_frame(X[k:k + 2], names) for k in range(len(X) - 1)])  # (M-1, 2, n_x)
    U0, U1 = model.lift(pairs[:, 0]), model.lift(pairs[:, 1])
    learn = record.progress[ok][:-1] <= learn_m

    # scaled lifted coordinates for the GP: U = D U~, u = E u~
    d = np.where(np.std(U0[learn], axis=0) > 1e-9, np.std(U0[learn], axis=0), 1.0)
    e = np.where(np.std(u[:-1][learn], axis=0) > 1e-9, np.std(u[:-1][learn], axis=0), 1.0)
    A_sc = model.A * d[None, :] / d[:, None]
    B_sc = model.B * e[None, :] / d[:, None]
    j = model.schedule_index                  # a scheduled input matrix: s B_s u = (d_j s~) B_s (e u~)
    scheduled = (model.B_s * e[None, :] / d[:, None] * d[j], j) if model.scheduled else ()
    vel, inputs = channel_rows(names, SHIPPED.gp_channels)
    varying = [i for i in range(n_x, model.n_K) if np.ptp(U0[learn, i]) > 1e-9]  # encoder outputs, not the constant
    B_d = np.zeros((model.n_K, len(vel)))
    B_d[vel, range(len(vel))] = 1.0
    comp = KoopmanCompensation(A_sc, B_sc, B_d, inputs + (varying if with_encoder else []), *scheduled)
    targets = comp.residual_target(U0[learn] / d, u[:-1][learn] / e, U1[learn] / d)
    n_z = comp.n_z
    hyp0 = SEHyper(sf2=np.maximum(np.var(targets.d, axis=0), 1e-8), ell=np.full(len(vel), np.sqrt(n_z)),
                   sn2=np.maximum(1e-2 * np.var(targets.d, axis=0), 1e-8))
    online = OnlineCompensator(comp, hyp0, nu=SHIPPED.gp_nu, m_max=SHIPPED.gp_m_max, n_max=SHIPPED.gp_n_max)
    for Ua, ua, Ub in zip(U0[learn] / d, u[:-1][learn] / e, U1[learn] / d):
        online.observe(Ua, ua, Ub)
    gp = online.refit()

    test = np.nonzero(~learn)[0]
    one = {}
    for label, g in (("nominal", None), ("compensated", gp)):
        pred = comp.predict(U0[test] / d, u[test] / e, g) * d
        err = pred[:, :n_x] - pairs[test, 1]
        one[label] = {n: float(np.sqrt(np.mean(err[:, i] ** 2))) for i, n in enumerate(names)}
    H = int(round(horizon_s / model.dt))
    starts = [k for k in test[::10] if k + H < len(X)]
    window = np.array([to_window_frame(X[k:k + H + 1], names) for k in starts])
    multi = {}
    for label, g in (("nominal", None), ("compensated", gp)):
        U = model.lift(window[:, 0]) / d
        for j in range(H):  # each step re-lifts the predicted state, keeping Upsilon = [x, rho_e(x)]
            U = np.array([comp.predict(Ui, ui, g) for Ui, ui in zip(U, u[np.array(starts) + j] / e)])
            U = model.lift(U[:, :n_x] * d[:n_x]) / d
        err = U[:, :n_x] * d[:n_x] - window[:, H]
        pos = [names.index("X"), names.index("Y")]
        multi[label] = {"position": float(np.sqrt(np.mean(np.sum(err[:, pos] ** 2, axis=1)))),
                        **{n: float(np.sqrt(np.mean(err[:, i] ** 2))) for i, n in enumerate(names) if i not in pos}}
    return {"gp_input": ", ".join([names[i] for i in inputs] + (["rho_e"] if with_encoder else []) + ["u"]), "learn_distance_m": learn_m, "learn_samples": int(learn.sum()), "test_samples": int(len(test)),
            "inducing_points": int(online.dictionary.m), "gp_fitted": gp is not None,
            "one_step_rmse": one, f"open_loop_{horizon_s:g}s_rmse": multi}


def steering_response(model: LiftedLinearModel, speeds=(1.5, 3.0, 6.0, 10.0, 15.0), delta: float = 0.05,
                      seconds: float = 2.0, params: str = "nominal") -> list[dict]:
    """Yaw rate after ``seconds`` of steering held at +-delta from straight driving at each speed
    (a_x = 0): the plant's (``params``) and the model's open-loop prediction (module docstring)."""
    cfg = BicycleConfig.load(params)
    steps = int(round(seconds / model.dt))
    names = model.state_names
    rows = []
    for v in speeds:
        row = {"speed": float(v)}
        for sign, key in ((1.0, "left"), (-1.0, "right")):
            u = np.array([0.0, sign * delta])
            straight = np.where(np.array(STATE_NAMES) == "vx", v, 0.0)       # at the origin, heading along X
            plant = DynamicBicycle(cfg, straight)
            for _ in range(steps):
                plant.step(u, model.dt)
            pred = model.rollout(straight[[STATE_NAMES.index(n) for n in names]], np.tile(u, (steps, 1)))
            row[f"plant_{key}"] = float(plant.state[STATE_NAMES.index("omega")])
            row[f"model_{key}"] = float(pred[-1, names.index("omega")])
            row[f"ratio_{key}"] = row[f"model_{key}"] / row[f"plant_{key}"]
        rows.append(row)
    return rows


def bench_dynamics(model: LiftedLinearModel, out: Path, seed: int = 0) -> dict:
    t = timings(model, seed)
    print(f"encoder + lift, one state:               {t['lift_s'] * 1e6:8.1f} us")
    sizes = f"{t['gp_inducing']} inducing, {t['gp_outputs']} out"
    print(f"GP mean + Jacobian ({sizes}): {t['gp_mean_jacobian_s'] * 1e6:8.1f} us (target <= 50 us)")
    print(f"GP full refit ({sizes}, {t['gp_samples']} samples): {t['gp_refit_s'] * 1e3:7.1f} ms (target <= 300 ms)")
    demos = [compensation_demo(model, seed, with_encoder=False), compensation_demo(model, seed, with_encoder=True)]
    for demo in demos:
        print(f"\nonline compensation on racing_track, 'exact' plant with process noise (seed {seed}), GP input "
              f"[{demo['gp_input']}]: learned on the first {demo['learn_distance_m']:g} m ({demo['learn_samples']} "
              f"samples, {demo['inducing_points']} inducing points), tested on the remaining {demo['test_samples']}")
        for title, key in (("one-step RMSE", "one_step_rmse"), ("1-s open-loop RMSE", "open_loop_1s_rmse")):
            rows = demo[key]
            chans = list(rows["nominal"])
            print(f"{title:<22}" + "".join(f"{c:>11}" for c in chans))
            for label in ("nominal", "compensated"):
                print(f"  {label:<20}" + "".join(f"{rows[label][c]:>11.5f}" for c in chans))
            ratio = {c: rows["nominal"][c] / max(rows["compensated"][c], 1e-15) for c in chans}
            print(f"  {'nominal/compensated':<20}" + "".join(f"{ratio[c]:>11.2f}" for c in chans))
    steer = steering_response(model)
    print("\nsteering response: yaw rate (rad/s) after 2 s of delta_f = +-0.05 rad from straight driving "
          "(a_x = 0), plant (nominal) and model")
    print(f"{'v m/s':>6}" + "".join(f"{h:>11}" for h in ("plant L", "model L", "model/pl", "plant R", "model R",
                                                          "model/pl")))
    for r in steer:
        print(f"{r['speed']:>6.1f}" + "".join(f"{r[k]:>11.3f}" for k in ("plant_left", "model_left", "ratio_left",
                                                                           "plant_right", "model_right", "ratio_right")))
    out.mkdir(parents=True, exist_ok=True)
    doc = {"timings": t, "compensation": demos, "steering_response": steer}
    (out / "bench_dynamics.json").write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {out / 'bench_dynamics.json'}")
    return doc
