"""Plain helpers shared by test modules (no fixtures, nothing built at import): where the LPIPS
weights are, the CLI commands invoked in-process, an avatar stage loaded with its renderer, and the
shape of the one-shot test capture. Workspaces the tests share are session fixtures in conftest.py."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def _lpips_weights() -> Path | None:
    """The LPIPS AlexNet weights where sage itself finds them ($SAGE_LPIPS_WEIGHTS, then
    ~/.cache/sage/lpips_alex_v0.1.pth), else None: tests that need them skip."""
    from sage_core.evaluate.lpips import find_lpips_weights

    try:
        return find_lpips_weights()
    except Exception:  # a named but missing file: treat as absent here, the CLI tests cover the error
        return None


LPIPS_WEIGHTS = _lpips_weights()
LPIPS_SKIP_REASON = "LPIPS weights not found: set SAGE_LPIPS_WEIGHTS or place lpips_alex_v0.1.pth in ~/.cache/sage/"

NOVEL_VIEWS = 3
"""Held-out cameras of the one-shot test capture (conftest's ``oneshot_ws``)."""
NOVEL_EXPRESSIONS = 1
"""Held-out expressions of the one-shot test capture."""


def commands_app() -> Any:
    """A local typer app with the deliverable commands (the real app registers them the same way)."""
    import typer

    from sage_cli.commands import demo_cmd, eval_cmd, export_cmd, reenact_cmd, run_cmd

    app = typer.Typer()
    app.command("eval")(eval_cmd.eval_)
    app.command("reenact")(reenact_cmd.reenact)
    app.command("export")(export_cmd.export)
    app.command("run")(run_cmd.run)
    app.command("demo")(demo_cmd.demo)
    return app


def invoke(args: list[Any], **env: str) -> Any:
    """Run ``sage <args>`` (eval, reenact, export, run, demo) in-process with LPIPS weights unset, a
    home folder without a cache and wide output; ``env`` adds or overrides variables. Returns typer's
    ``Result`` (exit_code, output)."""
    from typer.testing import CliRunner

    env = {"SAGE_LPIPS_WEIGHTS": "", "HOME": env.pop("HOME", "/nonexistent-home"), "COLUMNS": "200", **env}
    return CliRunner().invoke(commands_app(), [str(a) for a in args], env=env)


def load_phase1_renderer(ws: Path) -> tuple[Any, Any, Any]:
    """(ingested data, the loaded phase-1 :class:`StageAvatar`, its :class:`AvatarRenderer`) of a workspace."""
    from sage_core.data.dataset import IngestedData
    from sage_core.stages.avatars import AvatarRenderer, load_stage_avatar
    from sage_core.workspace import Workspace

    data = IngestedData.open(ws / "data")
    loaded = load_stage_avatar(Workspace(ws), "phase1", data)
    return data, loaded, AvatarRenderer(loaded.avatar, loaded.render)


def load_benchmark(name: str) -> Any:
    """The module of ``benchmarks/<name>.py`` (the scripts are not a package)."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
