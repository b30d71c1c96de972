"""Timing statistics of a long-running loop in constant memory: a histogram for the whole run
and a ring of the most recent samples for windowed percentiles."""

from __future__ import annotations

import numpy as np


class TimingStats:
    """Durations in seconds. The histogram has ``bin_s`` wide bins up to ``top_s`` (larger values
    land in the last bin; ``max_s`` keeps the exact maximum); ``recent`` holds the last
    ``window`` samples."""

    def __init__(self, bin_s: float = 1e-5, top_s: float = 0.1, window: int = 1000) -> None:
        self.bin_s = bin_s
        self.counts = np.zeros(int(round(top_s / bin_s)) + 1, dtype=np.int64)
        self.recent = np.zeros(window)
        self.n = 0
        self.max_s = 0.0
        self.total_s = 0.0

    def add(self, seconds: float) -> None:
        s = max(0.0, float(seconds))
        self.counts[min(int(s / self.bin_s), len(self.counts) - 1)] += 1
        self.recent[self.n % len(self.recent)] = s
        self.n += 1
        self.total_s += s
        if s > self.max_s:
            self.max_s = s

    def percentile(self, q: float) -> float:
        """The q-th percentile (0..100) over the whole run, to the bin's upper edge (s)."""
        if self.n == 0:
            return float("nan")
        idx = int(np.searchsorted(np.cumsum(self.counts), np.ceil(q / 100.0 * self.n)))
        return min((idx + 1) * self.bin_s, self.max_s)

    def recent_percentile(self, q: float) -> float:
        """The q-th percentile of the last ``window`` samples (s)."""
        if self.n == 0:
            return float("nan")
        return float(np.percentile(self.recent[: min(self.n, len(self.recent))], q))

    def over(self, limit_s: float) -> int:
        """How many samples exceeded ``limit_s`` (to bin resolution)."""
        return int(self.counts[int(np.ceil(limit_s / self.bin_s)):].sum())

    def summary(self) -> dict:
        return {"n": self.n, "p50_s": self.percentile(50), "p99_s": self.percentile(99), "max_s": self.max_s,
                "mean_s": self.total_s / self.n if self.n else float("nan")}
