"""Many subjects at once (``sage batch``): the SUBJECTS list, the local and Ray engines, per-subject
status files (written from the stages' events) and the batch summary."""

from __future__ import annotations

from .engines import Job, JobResult, run_job, run_local, run_ray, visible_gpus
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

__all__ = [
    "FIELDS",
    "METRIC_KEYS",
    "REGIMES",
    "STATUS_NAME",
    "SUMMARY_JSON",
    "SUMMARY_MD",
    "Job",
    "JobResult",
    "Subject",
    "StatusWriter",
    "SubjectOutcome",
    "load_subjects",
    "read_status",
    "run_job",
    "run_local",
    "run_ray",
    "stages_wall_time",
    "status_path",
    "subject_finished",
    "subject_metrics",
    "subject_spec",
    "summary_markdown",
    "visible_gpus",
    "write_status",
    "write_summary",
]
