"""Shared CLI pieces: option types, error handling, progress display, config resolution.

Only typer and rich are imported at module level, so ``sage --help`` stays instant.
"""

from __future__ import annotations

import contextlib
import logging
import math
import numbers
import time
from pathlib import Path
from typing import Annotated, Any, Callable, Iterator, Optional

import typer
from rich.console import Console
from rich.panel import Panel
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

console = Console(stderr=False, highlight=False)
err_console = Console(stderr=True, highlight=False)

# ---- shared option types -----------------------------------------------------------------
DeviceOpt = Annotated[str, typer.Option("--device", help="Device: auto, cpu or cuda[:N].")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Random seed of this stage (recorded in the manifest).")]
PresetOpt = Annotated[str, typer.Option("--preset", help="Settings preset: tiny (CPU, tests, demo: minutes), small (CPU, 256x372 captures, about 20k surfels: about a quarter of an hour on 2 idle cores) or default (the paper's, GPU).")]
ConfigOpt = Annotated[Optional[Path], typer.Option("--config", help="YAML/JSON config file; overrides the preset, flags override it.", exists=False)]
ForceOpt = Annotated[bool, typer.Option("--force", help="Redo the stage even if it finished with the same config and inputs.")]
VerboseOpt = Annotated[bool, typer.Option("--verbose/--quiet", help="Show detailed progress (default) or only errors and the final panel.")]
SetOpt = Annotated[Optional[list[str]], typer.Option("--set", help="Override any config field: --set key.sub=value (repeatable).")]
RenderBackendOpt = Annotated[Optional[str], typer.Option("--render-backend", help="Surfel rasterizer: auto (default), torch, cpp or triton (config field render_backend).")]
ThreadsOpt = Annotated[Optional[int], typer.Option("--threads", help="CPU threads of this process (default: $SAGE_THREADS, else the cores other processes are not keeping busy; `sage batch` shares the cores out). Recorded in the manifest.")]


def parse_sets(values: list[str] | None) -> dict[str, Any]:
    """``["a.b=1", "c=x"]`` -> ``{"a.b": "1", "c": "x"}`` (types are coerced by the config layer).

    A value without ``=`` or with an empty key is a ConfigError (exit code 3)."""
    from sage_core.errors import ConfigError

    out: dict[str, Any] = {}
    for v in values or []:
        k, eq, val = v.partition("=")
        if not eq or not k.strip():
            raise ConfigError(f"--set expects key=value (e.g. --set iterations=500), got {v!r}")
        out[k.strip()] = val.strip()
    return out


def require_workspace(ws: Path, hint: str = "") -> None:
    """The workspace folder must exist: WorkspaceError when ``ws`` is a file (or lies under one),
    InputError naming it when it is missing (``hint`` says which command creates what is needed)."""
    from sage_core.errors import InputError
    from sage_core.workspace import check_workspace_path

    check_workspace_path(ws)
    if not ws.is_dir():
        raise InputError(ws, "workspace folder not found" + hint)


def resolve_stage_config(stage: str, preset: str, config_file: Path | None, flags: dict[str, Any], regime: str | None = None) -> Any:
    """preset < regime defaults < config file < flags, for one stage."""
    from sage_core.config import load_config_file, resolve_config

    data = load_config_file(config_file) if config_file is not None else None
    return resolve_config(stage, preset, data, flags, file_label=str(config_file) if config_file else "config file", regime=regime)


@contextlib.contextmanager
def cli_errors() -> Iterator[None]:
    """Turn engine errors into one red line and the error's exit code; keyboard interrupt -> 130."""
    from sage_core.errors import SageError

    try:
        yield
    except SageError as e:
        err_console.print(f"[bold red]error:[/] {e}", soft_wrap=True)
        raise typer.Exit(code=e.exit_code) from None
    except KeyboardInterrupt:
        err_console.print("[yellow]interrupted[/]: the stage resumes from its last checkpoint when run again")
        raise typer.Exit(code=130) from None
    except MemoryError:
        err_console.print("[bold red]error:[/] out of memory: lower the image height (--height) or the surfel count, or use --preset tiny")
        raise typer.Exit(code=5) from None
    except OSError as e:
        # file-system refusals (permissions, read-only, a file where a folder belongs, full disk): exit 2
        import errno

        if e.errno not in (errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.EISDIR, errno.EEXIST, errno.ENOSPC):
            raise
        where = f"{e.filename}: " if e.filename else ""
        err_console.print(f"[bold red]error:[/] {where}{e.strerror or e}", soft_wrap=True)
        raise typer.Exit(code=2) from None
    except RuntimeError as e:
        if "out of memory" in str(e).lower():
            err_console.print("[bold red]error:[/] the device ran out of memory: lower the image height, the surfel count or the batch/chunk sizes in the config")
            raise typer.Exit(code=5) from None
        raise


LONG_STAGE_S = 2 * 3600.0
"""A stage expected to train longer than this on a CPU gets a hint naming the preset that fits."""


def estimate_lines(title: str, estimate_s: float, s_per_step: float, device: str | None, preset: str | None,
                   basis: str = "its first steps") -> list[str]:
    """What the CLI prints when a training loop reports its first duration estimate: one line with the
    estimate and its basis, and on a CPU a warning naming the preset when it is ``default`` (the
    paper's GPU settings) or the stage would take longer than :data:`LONG_STAGE_S`, with the preset
    that fits."""
    from sage_core.config import PRESETS
    from sage_core.runtime import format_duration

    where = f"on this device ({device})" if device else "on this device"
    lines = [f"[bold]{title}[/]: about {format_duration(estimate_s)} {where} ({s_per_step:.2f} s/step over {basis}; updated as it runs)"]
    if device != "cpu" or preset is None:
        return lines
    size = {"tiny": 0, "small": 1, "default": 2}
    smaller = [p for p in ("small", "tiny") if p in PRESETS and size[p] < size.get(preset, 0)]
    fits = smaller[0] if smaller else None
    if preset == "default" or estimate_s > LONG_STAGE_S:
        hint = f"--preset {fits} fits a CPU" if fits else "lower --iterations or the surfel count to finish sooner"
        lines.append(f"[yellow]warning:[/] preset '{preset}' on a CPU: {title} will take about {format_duration(estimate_s)}; {hint}")
    return lines


ESTIMATE_CHANGE = 0.25
"""An updated duration estimate is printed when it moves the expected end by more than this share of
the remaining time printed before (every update goes to the log)."""


class ProgressDisplay:
    """A rich progress bar fed by the engine's ``progress(done, total, message=..., **stats)`` callback
(:class:`sage_cli._stage.StageDisplay` feeds it the stages' events; the stage functions write the
progress lines of the log file).

    A call carrying ``estimate_s`` (and ``s_per_step``, ``estimate_basis``; :meth:`sage_core.runtime.Estimate.as_stats`)
    prints the stage's expected duration with its basis, with :func:`estimate_lines`, and later
    updates that move it by more than :data:`ESTIMATE_CHANGE`; ``device`` and ``preset`` say which
    hint applies.
    """

    def __init__(self, title: str, enabled: bool = True, device: str | None = None, preset: str | None = None) -> None:
        self.title = title
        self.enabled = enabled
        self.device = device
        self.preset = preset
        self._progress: Progress | None = None
        self._task: Any = None
        self._log = logging.getLogger("sage")
        self._shown: tuple[float, float] | None = None  # (expected end, remaining) of the estimate last printed

    def __enter__(self) -> "ProgressDisplay":
        if self.enabled:
            self._progress = Progress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[rate]}"),
                TimeElapsedColumn(),
                TimeRemainingColumn(),
                TextColumn("{task.fields[info]}"),
                console=console,
                transient=False,
            )
            self._progress.__enter__()
            self._task = self._progress.add_task(self.title, total=None, info="", rate="")
        self._t0 = time.time()
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._progress is not None:
            self._progress.__exit__(*exc)

    def __call__(self, done: int, total: int | None = None, message: str = "", **stats: Any) -> None:
        if "estimate_s" in stats:
            self._estimate(message or self.title, stats)
            return
        info = message
        if stats:
            info = (message + "  " if message else "") + "  ".join(_fmt_stat(k, v) for k, v in stats.items())
        elapsed = max(time.time() - self._t0, 1e-9)
        rate = f"{done / elapsed:.1f} it/s" if done else ""
        if self._progress is not None:
            self._progress.update(self._task, completed=done, total=total, info=info, rate=rate)

    def _estimate(self, title: str, stats: dict[str, Any]) -> None:
        """Print a loop's first estimate (:func:`estimate_lines`); an update only when it moves the
        expected end by more than :data:`ESTIMATE_CHANGE` of the remaining time printed before. All
        go to the log."""
        from sage_core.runtime import format_duration

        total_s, s_per_step = float(stats["estimate_s"]), float(stats.get("s_per_step", float("nan")))
        remaining = float(stats.get("remaining_s", 0.0))
        basis = str(stats.get("estimate_basis", "its first steps"))
        end = time.time() + remaining
        if stats.get("estimate_first", True) or self._shown is None:
            lines = estimate_lines(title, total_s, s_per_step, self.device, self.preset, basis)
        else:
            lines = [f"[bold]{title}[/]: now about {format_duration(remaining)} to go, {format_duration(total_s)} in all "
                     f"({s_per_step:.2f} s/step over {basis})"]  # fmt: skip
            shown_end, shown_remaining = self._shown
            if abs(end - shown_end) <= ESTIMATE_CHANGE * max(shown_remaining, 1.0):
                self._log.info("%s", _plain(lines[0]))
                return
        self._shown = (end, remaining)
        for line in lines:
            self._log.info("%s", _plain(line))
            if self.enabled or "warning" in line:
                console.print(line, soft_wrap=True)


def _plain(line: str) -> str:
    """A line without its rich markup."""
    return line.replace("[bold]", "").replace("[/]", "").replace("[yellow]", "")


MISSING = "—"
"""What the panels and tables show for a metric that was not measured (None or NaN)."""


def fmt_metric(v: Any, spec: str = ".4g") -> str:
    """A metric for display: ``format(v, spec)``, or :data:`MISSING` where there is no value
    (None, NaN, or anything that is not a real number; a bool is not a metric)."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or math.isnan(v):
        return MISSING
    return format(v, spec)


def _fmt_stat(k: str, v: Any) -> str:
    if isinstance(v, float):
        return f"{k} {fmt_metric(v)}"
    return f"{k} {v}"


def summary_panel(title: str, rows: list[tuple[str, Any]], paths: list[tuple[str, Path]] | None = None) -> None:
    """The panel that ends every command: numbers, then the files written."""
    t = Table.grid(padding=(0, 2))
    t.add_column(style="bold cyan")
    t.add_column()
    for k, v in rows:
        t.add_row(k, _fmt_value(v))
    for k, p in paths or []:
        t.add_row(k, str(p))
    console.print(Panel(t, title=title, expand=False))


def _fmt_value(v: Any) -> str:
    if isinstance(v, float):
        return fmt_metric(v)
    if isinstance(v, (list, tuple)):
        return ", ".join(_fmt_value(x) for x in v)
    return str(v)


def run_guarded(fn: Callable[[], None]) -> None:
    """Run a command body under :func:`cli_errors`."""
    with cli_errors():
        fn()
