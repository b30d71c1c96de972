"""When the daemon gives up control: the checks of each tick and of the health monitor.

Each check returns None when all is well, or a reason ``"<kind>: <detail>"`` with kind one of
``REASONS``. What happens then (the platform's safe action, within two ticks, logged as an event,
latched until the daemon exits with code 3) is the control loop's job.
"""

from __future__ import annotations

import numpy as np

from vflpcd.core.ports import StampedState
from vflpcd.core.safety.monitors import REASONS as MONITOR_REASONS
from vflpcd.daemon.config import FailsafePolicy

REASONS = ("link_lost", "no_state", "stale_state", "nonfinite_state", "controller_error", "nonfinite_command",
           "overrun_streak", "stall", "collision") + MONITOR_REASONS    # the last two: vflpcd.core.safety


class FailsafeMonitor:
    def __init__(self, policy: FailsafePolicy, n_x: int) -> None:
        self.policy, self.n_x = policy, n_x
        self.streak = 0

    def check_state(self, stamped: StampedState | None, now_ns: int, link_fault: str | None) -> str | None:
        """The platform link and the state to be used at a tick starting at ``now_ns``."""
        if link_fault:
            return f"link_lost: {link_fault}"
        if stamped is None:
            return "no_state: the platform has not reported a state"
        age = (now_ns - stamped.stamp_ns) * 1e-9
        if age > self.policy.state_max_age:
            return f"stale_state: {age * 1e3:.0f} ms old (limit {self.policy.state_max_age * 1e3:.0f} ms)"
        x = np.asarray(stamped.state)
        if x.shape != (self.n_x,) or not np.all(np.isfinite(x)):
            bad = [i for i, v in enumerate(np.ravel(x)) if not np.isfinite(v)]
            return f"nonfinite_state: state of shape {x.shape} with non-finite entries {bad[:6]}"
        return None

    def check_command(self, u: np.ndarray, n_u: int) -> str | None:
        u = np.asarray(u, dtype=float)
        if u.shape != (n_u,) or not np.all(np.isfinite(u)):
            return f"nonfinite_command: {np.ravel(u).tolist()!r}"
        return None

    def after_tick(self, overrun: bool) -> str | None:
        """Count consecutive overruns; a reason once the streak reaches the policy's limit."""
        self.streak = self.streak + 1 if overrun else 0
        if self.streak >= self.policy.overrun_streak:
            return f"overrun_streak: {self.streak} consecutive ticks ran past their deadline"
        return None

    def stalled(self, now_ns: int, last_tick_ns: int) -> str | None:
        """For the health monitor (outside the control thread): no tick finished for too long."""
        gap = (now_ns - last_tick_ns) * 1e-9
        if gap > self.policy.stall:
            return f"stall: no control tick finished for {gap * 1e3:.0f} ms (limit {self.policy.stall * 1e3:.0f} ms)"
        return None
