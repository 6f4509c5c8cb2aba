"""Machinery of ``benchmarks/suite.py``: rows and sizes, the plan of ``sage`` commands, running
them with wall time and peak memory, collecting each row's numbers, and the results document."""

from __future__ import annotations

from .execute import collect_row, execute, step_command
from .report import machine_info, merge_results, render_document, render_markdown
from .rows import ROW_IDS, ROWS, SIZES, RowSpec, Settings, Size, Step, parse_overrides, plan, smoke_size
from .runner import ProcResult, command_line, run_process, sage_argv

__all__ = [
    "ROWS", "ROW_IDS", "SIZES", "RowSpec", "Settings", "Size", "Step", "ProcResult",
    "collect_row", "command_line", "execute", "machine_info", "merge_results", "parse_overrides", "plan",
    "render_document", "render_markdown", "run_process", "sage_argv", "smoke_size", "step_command",
]
