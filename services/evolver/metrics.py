"""Prometheus metrics of the evolver service: jobs, episodes, phase progress, success per round."""

from prometheus_client import Counter, Gauge

JOBS = Gauge("zetta_evolver_jobs", "Evolution jobs by state", ["state"])
EPISODES = Counter("zetta_evolver_episodes_total", "Episodes finished (run or read back from the store)", ["job_id"])
PHASE_PROGRESS = Gauge("zetta_evolver_phase_progress_ratio", "Finished share of the current phase's episodes", ["job_id"])
ROUND = Gauge("zetta_evolver_round", "Round of the phase running now (0: final evaluation)", ["job_id"])
SUCCESS = Gauge("zetta_evolver_success_ratio", "Success rate per task, round and arm (dev, heldout_bare, heldout_final)",
                ["job_id", "task", "round", "arm"])
ADMITTED = Gauge("zetta_evolver_admitted_versions", "Harness versions admitted by the gates", ["job_id"])
