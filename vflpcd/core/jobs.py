"""One flow for a controller's background work (``WorkerJobs``): take a job, run it, install its
outcome. ``run_replan`` and ``run_refit`` are what a worker runs (the daemon's worker processes,
``vflpcd.daemon.workers``); ``run_inline`` does the whole flow at once, between two ticks (the
offline runner and the benchmarks)."""

from __future__ import annotations

from vflpcd.core.dynamics.compensation import RefitJob, refit_job
from vflpcd.core.guidance.implicit import GuidanceError
from vflpcd.core.ports import WorkerJobs
from vflpcd.core.vflpc import PlanResult, ReplanJob, plan_job


def run_replan(planner, job: ReplanJob) -> PlanResult:
    """A replan on ``planner`` (GuidanceError when it finds no plan)."""
    return plan_job(planner, job)


def run_refit(job: RefitJob):
    """A GP refit (the new model, or the previous one when the fit is rejected)."""
    return refit_job(job)


def run_inline(jobs: WorkerJobs) -> int:
    """The replan that the last step found due (the next step uses its result), then the GP refit
    when one is due. Returns how many jobs ran (0, 1 or 2)."""
    ran = 0
    job = jobs.take_replan()
    if job is not None:
        ran += 1
        try:
            jobs.install_plan(job, run_replan(jobs.planner, job))
        except GuidanceError as exc:
            jobs.replan_failed(job, str(exc))
    refit = jobs.take_refit()
    if refit is not None:
        ran += 1
        jobs.install_model(refit, run_refit(refit))
    return ran
