"""Many subjects at once (``sage batch``): the SUBJECTS list, the local and Ray engines with the local
sharing of GPUs and cores, the worker that runs one subject, per-subject status files (written from
the stages' events), the batch process's bookkeeping and the batch summary."""

from __future__ import annotations

from .driver import BatchDriver
from .engines import Job, JobResult, run_job, run_local, run_ray, visible_gpus
from .plan import LocalPlan, local_gpus, plan_local
from .progress import StatusWriter
from .specs import subject_spec
from .subjects import FIELDS, REGIMES, Subject, load_subjects
from .summary import (
    METRIC_KEYS,
    STATUS_NAME,
    SUMMARY_JSON,
    SUMMARY_MD,
    SubjectOutcome,
    read_status,
    stages_wall_time,
    status_path,
    subject_finished,
    subject_metrics,
    summary_markdown,
    write_status,
    write_summary,
)
from .worker import WorkerArgs, check_spec, exit_state, parse_worker_args, run_subject, spec_flags, watch_parent, worker_argv

__all__ = [
    "BatchDriver",
    "FIELDS",
    "METRIC_KEYS",
    "REGIMES",
    "STATUS_NAME",
    "SUMMARY_JSON",
    "SUMMARY_MD",
    "Job",
    "JobResult",
    "LocalPlan",
    "Subject",
    "StatusWriter",
    "SubjectOutcome",
    "WorkerArgs",
    "exit_state",
    "load_subjects",
    "local_gpus",
    "parse_worker_args",
    "plan_local",
    "read_status",
    "run_job",
    "run_local",
    "run_ray",
    "check_spec",
    "run_subject",
    "spec_flags",
    "stages_wall_time",
    "status_path",
    "subject_finished",
    "subject_metrics",
    "subject_spec",
    "summary_markdown",
    "visible_gpus",
    "watch_parent",
    "worker_argv",
    "write_status",
    "write_summary",
]
