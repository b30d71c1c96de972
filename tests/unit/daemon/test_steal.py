"""The host's steal counter: read from /proc/stat's cpu line, and which ticks began while it grew."""

import numpy as np
import pytest

from vflpcd.app.steal import StealSampler, read_steal


def test_the_steal_column_of_the_cpu_line_is_read_and_a_file_without_it_gives_none(tmp_path):
    stat = tmp_path / "stat"
    stat.write_text("cpu  100 2 30 4000 5 0 6 77 0 0\ncpu0 50 1 15 2000 2 0 3 40 0 0\n")
    assert read_steal(stat) == 77
    stat.write_text("intr 1 2 3\n")
    assert read_steal(stat) is None
    assert read_steal(tmp_path / "missing") is None


def _sampler(stamps_ms, counts):
    s = StealSampler(period_s=0.1)
    s.stamps = [int(t * 1e6) for t in stamps_ms]
    s.counts = list(counts)
    return s


def test_a_tick_counts_as_stolen_only_when_the_counter_grew_within_a_period_of_its_start():
    # samples every 100 ms; the counter grows once, between 300 and 400 ms
    s = _sampler([0, 100, 200, 300, 400, 500, 600, 700], [5, 5, 5, 5, 6, 6, 6, 6])
    ticks = np.array([50, 250, 350, 420, 550, 650]) * 1_000_000
    assert s.stolen_near(ticks).tolist() == [False, True, True, True, False, False]
    # a tick whose window leaves the sampled span is not called stolen
    assert s.stolen_near(np.array([690_000_000, -5_000_000])).tolist() == [False, False]


def test_the_share_is_the_stolen_cpu_time_over_the_span_and_the_cpus():
    from vflpcd.app import steal

    s = _sampler([0, 1000], [0, steal.USER_HZ // 10])     # 0.1 s of one CPU stolen in 1 s of two CPUs
    assert s.share(cpus=2) == pytest.approx(0.05)


def test_without_a_counter_nothing_is_sampled_and_every_answer_is_none():
    s = StealSampler(period_s=0.01, read=lambda: None).start()
    s.stop()
    assert not s.available and s.share() is None and s.stolen_near(np.array([1, 2])) is None


def test_a_sampler_on_this_machine_samples_until_stopped():
    s = StealSampler(period_s=0.01)
    if read_steal() is None:
        pytest.skip("no /proc/stat steal column here")
    s.start()
    import time

    time.sleep(0.1)
    s.stop()
    assert len(s.counts) >= 5 and s.counts == sorted(s.counts) and 0.0 <= s.share() <= 1.0
