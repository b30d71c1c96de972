"""The steps of eq. (xi_r) (``grid.integrate``) as one plain loop to compile.

One step at xi_k = (x, y): the path's chi_P^ interpolated between the four nodes of the global
grid around xi_k (bilinear, made a unit vector again; ``grid``'s module docstring), times the
cup_Q_i of each static obstacle whose local grid holds xi_k (its chi_R_i^ for the decided gamma_i
added with weight 1 - cup), then each mover and each acting virtual obstacle evaluated at xi_k
(the mover where it is at the step's time), normalised; |chi_c| < epsilon reuses the previous
direction. The loop stops and returns when it needs what only the caller can give, with ``aux``
saying what, and the caller calls it again: it resumes at the step it stopped at.

- ``FILL``: the global grid's block aux = (bi, bj) is not computed yet (``PathGrid.fill``);
- ``ENTERED``: the trajectory entered static obstacle aux[0]'s reactive region (at its grid's
  cell aux[1], aux[2]) for the first time and its gamma_i must be decided from the path's tangent
  (``grid``'s side rule);
- ``LEFT_GRID``, ``VANISHED``: the errors (the point left the grid; the field vanished at the
  start with no heading to inherit);
- ``REACHED``: the progress reached x_end; ``OUT_OF_STEPS``: max_steps were taken.

Arrays, all float64 but ``filled`` (bool), ``virtual_off`` and ``aux`` (int64):

- ``state`` (7,): x, y, the previous direction (ux, uy), 1.0 if there is one, the inherited steps,
  the step k (read at entry, written at return);
- ``xy`` (max_steps + 1, 2): xy[0] the start, step k writes xy[k + 1];
- ``pdata`` (nx, ny, 2), ``filled`` (nbx, nby) and ``pgrid`` (ox, oy, 1 / h, block): the global grid;
- ``statics`` (S, 6): per static obstacle its local grid's origin x, y, cells nx, ny, offset into
  ``sdata`` (the grids' (nx, ny, 5) data flattened one after the other) and the side rule's gamma;
  ``gammas`` (S,): the decided gamma_i, 0.0 while undecided;
- ``movers`` (M, 13): each an ``ObstacleImplicit.row`` (centre, velocity, stamp, squared reach,
  yaw, axes, p, c) and its gamma;
- ``virtuals`` (V, 18): centre x, y, radius, c, gamma, x_stop, and the parent's
  ``ObstacleImplicit.row``; ``virtual_off`` (V,): the step it stopped acting, -1 none;
- ``params`` (14,): l1, l2, k_c, k_r, epsilon, beta, x_end, max_steps, progress origin x, y and
  direction x, y (progress = (xi - po) . pd), t0, speed; ``step_times`` (T,) (T = 0: none).

Run interpreted (where numba is missing) it is the same arithmetic, number for number; compiled
(``vflpcd.controllers.loops``) ``step_time`` and ``primitives``' ``cup_at``, ``guiding_at``,
``row_centre`` and ``superellipse_at`` are compiled with it.
"""

from __future__ import annotations

import math

from vflpcd.core.guidance.primitives import cup_at, guiding_at, row_centre, superellipse_at

REACHED, OUT_OF_STEPS, FILL, LEFT_GRID, VANISHED, ENTERED = 0, 1, 2, 3, 4, 5


def step_time(k: int, t0: float, beta: float, speed: float, step_times) -> float:
    """When the trajectory reaches step k: from step_times (K,) (an array or a list) where known,
    else at ``speed``."""
    if step_times is not None and len(step_times):
        if k < len(step_times):
            return float(step_times[k])
        return float(step_times[-1]) + (k - len(step_times) + 1) * beta / max(speed, 1e-3)
    return t0 + k * beta / max(speed, 1e-3)


def step_loop(state, xy, pdata, filled, pgrid, statics, sdata, gammas, movers, virtuals, virtual_off,
              params, step_times, aux):
    """Steps from ``state`` until one of the returns above (module docstring)."""
    x, y = state[0], state[1]
    ux, uy, has_prev = state[2], state[3], state[4] > 0.0
    inherited, k0 = int(state[5]), int(state[6])
    ox, oy, inv_h, block = pgrid[0], pgrid[1], pgrid[2], int(pgrid[3])
    nx, ny = pdata.shape[0], pdata.shape[1]
    l1, l2, k_c, k_r, epsilon, beta, x_end = params[0], params[1], params[2], params[3], params[4], params[5], params[6]
    max_steps = int(params[7])
    pox, poy, pdx, pdy, t0, speed = params[8], params[9], params[10], params[11], params[12], params[13]
    status = OUT_OF_STEPS
    k = k0
    while k < max_steps:
        gi, gj = (x - ox) * inv_h, (y - oy) * inv_h     # the node below and left of xi_k, and the weights
        if not (-0.5 <= gi < nx - 0.5 and -0.5 <= gj < ny - 0.5):
            status = LEFT_GRID
            break
        i0, j0 = min(max(int(math.floor(gi)), 0), max(nx - 2, 0)), min(max(int(math.floor(gj)), 0), max(ny - 2, 0))
        i1, j1 = min(i0 + 1, nx - 1), min(j0 + 1, ny - 1)
        wi, wj = min(max(gi - i0, 0.0), 1.0), min(max(gj - j0, 0.0), 1.0)
        missing = False
        for ci in (i0, i1):
            for cj in (j0, j1):
                if not missing and not filled[ci // block, cj // block]:
                    aux[0], aux[1] = ci // block, cj // block
                    missing = True
        if missing:
            status = FILL
            break
        P, Vx, Vy = 1.0, 0.0, 0.0
        undecided = -1
        for n in range(statics.shape[0]):
            gx0, gy0, gnx, gny, off = statics[n, 0], statics[n, 1], int(statics[n, 2]), int(statics[n, 3]), int(statics[n, 4])
            fa, fb = (x - gx0) * inv_h, (y - gy0) * inv_h
            if not (-0.5 <= fa < gnx - 0.5 and -0.5 <= fb < gny - 0.5):
                continue
            at = off + (int(fa + 0.5) * gny + int(fb + 0.5)) * 5
            cup = sdata[at]
            if cup == 1.0:
                continue
            if gammas[n] == 0.0:
                undecided = n
                aux[1], aux[2] = int(fa + 0.5), int(fb + 0.5)
                break
            rx, ry = (sdata[at + 1], sdata[at + 2]) if gammas[n] > 0 else (sdata[at + 3], sdata[at + 4])
            P *= cup
            Vx, Vy = Vx + (1.0 - cup) * rx, Vy + (1.0 - cup) * ry
        if undecided >= 0:
            aux[0] = undecided
            status = ENTERED
            break
        if movers.shape[0] > 0:
            t = step_time(k, t0, beta, speed, step_times)
            for m in range(movers.shape[0]):
                cx, cy = row_centre(movers, m, t)
                if (x - cx) ** 2 + (y - cy) ** 2 > movers[m, 5]:
                    continue
                phi, gx, gy = superellipse_at(x, y, cx, cy, movers[m, 6], movers[m, 7], movers[m, 8], movers[m, 9],
                                              movers[m, 10])
                cup = cup_at(phi, movers[m, 11], l1, l2)
                chx, chy = guiding_at(movers[m, 12], k_r, phi, gx, gy)
                chn = max(math.hypot(chx, chy), 1e-300)
                P *= cup
                Vx, Vy = Vx + (1.0 - cup) * chx / chn, Vy + (1.0 - cup) * chy / chn
        free = P == 1.0  # outside every actual reactive region: where virtual obstacles may act
        progress = (x - pox) * pdx + (y - poy) * pdy
        for n in range(virtuals.shape[0]):
            if virtual_off[n] >= 0:
                continue
            dx, dy = x - virtuals[n, 0], y - virtuals[n, 1]
            radius = virtuals[n, 2]
            r = (dx * dx + dy * dy) ** 0.5
            if r >= radius or r == 0.0:
                continue
            pcx, pcy = row_centre(virtuals[:, 6:], n, 0.0)
            parent = superellipse_at(x, y, pcx, pcy, virtuals[n, 12], virtuals[n, 13], virtuals[n, 14], virtuals[n, 15],
                                     virtuals[n, 16])[0]
            if progress >= virtuals[n, 5] or parent <= 0.0:
                virtual_off[n] = k  # past the entry into R_actl, or inside it (remark 2): stop acting
                continue
            if not free:
                continue
            # circle virtual obstacle: varphi = r / radius - 1, grad = (dx, dy) / (r radius)
            cv, gamma = virtuals[n, 3], virtuals[n, 4]
            phi = r / radius - 1.0
            s_i = 0.0 if phi <= cv else math.exp(k_c / (cv - phi))
            gx, gy = dx / (r * radius), dy / (r * radius)
            kx, ky = guiding_at(gamma, k_r, phi - cv, gx, gy)  # gamma E grad - k_r (varphi - c) grad
            kn = (kx * kx + ky * ky) ** 0.5
            P *= s_i
            Vx, Vy = Vx + (1.0 - s_i) * kx / kn, Vy + (1.0 - s_i) * ky / kn
        px = ((1.0 - wi) * ((1.0 - wj) * pdata[i0, j0, 0] + wj * pdata[i0, j1, 0])
              + wi * ((1.0 - wj) * pdata[i1, j0, 0] + wj * pdata[i1, j1, 0]))
        py = ((1.0 - wi) * ((1.0 - wj) * pdata[i0, j0, 1] + wj * pdata[i0, j1, 1])
              + wi * ((1.0 - wj) * pdata[i1, j0, 1] + wj * pdata[i1, j1, 1]))
        pn = (px * px + py * py) ** 0.5
        if pn > 0.0:
            px, py = px / pn, py / pn
        cx, cy = P * px + Vx, P * py + Vy
        norm = (cx * cx + cy * cy) ** 0.5
        if norm < epsilon:
            if not has_prev:
                status = VANISHED
                break
            inherited += 1
        else:
            ux, uy = cx / norm, cy / norm
            has_prev = True
        x, y = x + beta * ux, y + beta * uy
        k += 1
        xy[k, 0], xy[k, 1] = x, y
        if (x - pox) * pdx + (y - poy) * pdy >= x_end:
            status = REACHED
            break
    state[0], state[1], state[2], state[3] = x, y, ux, uy
    state[4] = 1.0 if has_prev else 0.0
    state[5], state[6] = float(inherited), float(k)
    return status
