"""Workers: replans and refits run in another process and come back whole; failures are reported,
a dead worker process is replaced, and nothing blocks the caller."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from processes import proc_info, wait_gone
from vflpcd.controllers.vflpc import make_vflpc
from sim.plants import make_plant
from vflpcd.config.scenarios import line_scenario_toml, load_scenario
from vflpcd.core.guidance.implicit import GuidanceError
from vflpcd.core.vflpc import plan_job
from vflpcd.daemon.workers import Workers


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    f = tmp_path_factory.mktemp("w") / "line.toml"
    f.write_text(line_scenario_toml("line", length=80.0))
    sc = load_scenario(f)
    ctl = make_vflpc(sc, compensation=True)
    plant = make_plant(sc, 0)
    for k in range(200):                                   # samples for the GP, and a due replan
        u = ctl.step(plant.state, k * 0.05)
        plant.step(u, 0.05)
    workers = Workers("process", ctl.planner)
    workers.start()
    yield ctl, workers
    workers.close()


def wait(workers, timeout=30.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        done = workers.collect()
        if done:
            return done
        time.sleep(0.01)
    raise AssertionError("no job finished")


def test_a_replan_in_another_process_equals_the_local_one(setup):
    ctl, workers = setup
    job = ctl.take_replan(force_at=10.0)
    t0 = time.perf_counter()
    assert workers.submit("replan", job)
    assert time.perf_counter() - t0 < 0.05                 # submitting does not wait for the plan
    assert not workers.submit("replan", job)               # one job of a kind at a time
    (done,) = wait(workers)
    assert done.kind == "replan" and done.error is None and done.latency_s > 0
    local = plan_job(ctl.planner, job)
    np.testing.assert_allclose(done.result.plan.trajectory.sample(np.array([10.5]))["pos"],
                               local.plan.trajectory.sample(np.array([10.5]))["pos"])
    before = ctl.replans
    ctl.install_plan(done.job, done.result)
    assert ctl.replans == before + 1 and ctl._plan is done.result.plan


def test_a_refit_in_another_process_is_installed(setup):
    ctl, workers = setup
    ctl._since_refit = ctl.params.refit_every
    job = ctl.take_refit()
    assert job is not None and workers.submit("refit", job)
    (done,) = wait(workers)
    assert done.error is None and done.result is not None
    ctl.install_model(done.job, done.result)
    assert ctl.compensator.model is not None and ctl.refits >= 1


def test_a_failing_replan_is_reported_not_raised(setup):
    ctl, workers = setup
    job = ctl.take_replan(force_at=11.0)
    inside = type(job)(job.s, np.array([40.0, 0.0]), job.vel, job.heading, job.t,
                       (job.obstacles + tuple(make_wall())))
    assert workers.submit("replan", inside)
    (done,) = wait(workers)
    assert isinstance(done.error, GuidanceError)


def test_a_killed_worker_is_replaced(setup):
    ctl, workers = setup
    job = ctl.take_replan(force_at=12.0)
    assert workers.submit("replan", job)
    pid = next(iter(workers._executors["replan"]._processes))
    os.kill(pid, signal.SIGKILL)
    (done,) = wait(workers)
    assert done.error is not None and workers.restarts == 1
    assert workers.submit("replan", job)                   # a fresh pool takes the next job
    (done,) = wait(workers, 60.0)
    assert done.error is None


def make_wall():
    from vflpcd.core.obstacles import ObstacleState
    from vflpcd.core.shapes import Circle

    return [ObstacleState("wall", Circle(3.0), np.array([40.0, 0.0]), 0.0, np.zeros(2), 0.0)]


# Dying with the parent (vflpcd.daemon.lifeline): a parent process that starts a child, prints
# the pids to watch, then waits to be SIGKILLed by the test.

PARENT = """
import subprocess, sys, threading, time
from vflpcd.daemon import lifeline
from vflpcd.daemon.workers import Workers

if __name__ == "__main__":
    how = sys.argv[1]
    if how == "workers":                 # started by a thread that then ends
        workers = Workers("process", None)
        starter = threading.Thread(target=workers.start)
        starter.start()
        starter.join()
        pids = [p.pid for ex in workers._executors.values() for p in ex._processes.values()]
    else:
        watch = [sys.executable, "-c", "import sys, time; from vflpcd.daemon import lifeline; "
                 "lifeline.watch(int(sys.argv[1])); time.sleep(60)", str(__import__("os").getpid())]
        argv = {"watch": watch, "pdeathsig": ["sleep", "60"], "none": ["sleep", "60"]}[how]
        child = subprocess.Popen(argv, preexec_fn=lifeline.preexec() if how == "pdeathsig" else None)
        pids = [child.pid]
        time.sleep(1.0)                  # the watch thread has started
    print(" ".join(map(str, pids)), flush=True)
    time.sleep(120)
"""


@pytest.mark.parametrize("how", ["watch", "pdeathsig", "workers", "none"])
def test_a_child_dies_with_its_sigkilled_parent(tmp_path, how):
    script = tmp_path / "parent.py"
    script.write_text(PARENT)
    parent = subprocess.Popen([sys.executable, str(script), how], stdout=subprocess.PIPE, text=True)
    children = []
    try:
        line = parent.stdout.readline()
        children = [proc_info(int(pid)) for pid in line.split()]
        assert children and all(c is not None and c.ppid == parent.pid for c in children), line
        time.sleep(0.5)
        assert all(c.alive() for c in children)            # they live while the parent does
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait(5.0)
        left = wait_gone(children, 2.0)
        if how == "none":                                  # the control: without a lifeline, an orphan
            assert left == children
        else:
            assert not left, left
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait(5.0)
        parent.stdout.close()
        for c in children:
            if c is not None and c.alive():
                os.kill(c.pid, signal.SIGKILL)


@pytest.mark.parametrize("call", ["watch", "arm"])
def test_a_child_whose_parent_is_gone_already_is_killed_at_once(call):
    not_its_parent = os.getppid()      # what the child sees after its parent died: another parent
    run = subprocess.run([sys.executable, "-c", f"from vflpcd.daemon import lifeline; "
                          f"lifeline.{call}({not_its_parent}); print('survived')"],
                         capture_output=True, text=True, timeout=30)
    assert run.returncode == -signal.SIGKILL and "survived" not in run.stdout, run.stderr


def test_a_watched_child_lives_on_while_its_parent_does():
    run = subprocess.run([sys.executable, "-c", "import os, time; from vflpcd.daemon import lifeline; "
                          "lifeline.watch(os.getppid()); time.sleep(0.3); print('alive')"],
                         capture_output=True, text=True, timeout=30)
    assert run.returncode == 0 and run.stdout.strip() == "alive", run.stderr


WARMED_CHILD = """
import pickle, sys
from vflpcd.daemon import workers
planner, job = pickle.load(open(sys.argv[1], "rb"))
workers._init_worker(planner)
workers._warm_up()
before = set(sys.modules)
workers._run_replan(job)
print(" ".join(sorted(set(sys.modules) - before)))
"""


def test_a_warmed_worker_imports_nothing_at_its_first_replan(setup, tmp_path):
    """What a spawned worker loads before its first job (``_warm_up``) is all its replans import: a
    module imported inside the planning code (scipy.ndimage, 0.2-0.5 s) made the first replan of
    every worker that long."""
    import pickle

    ctl, _ = setup
    f = tmp_path / "job.pkl"
    f.write_bytes(pickle.dumps((ctl.planner, ctl.take_replan(force_at=10.0))))
    out = subprocess.run([sys.executable, "-c", WARMED_CHILD, str(f)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == ""
