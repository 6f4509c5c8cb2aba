"""The ``sage`` command: one sub-command per stage. Heavy imports happen inside the commands."""

from __future__ import annotations

import typer

from sage_core._version import __version__

app = typer.Typer(
    name="sage",
    help=(
        "SAGE: animatable 2D Gaussian surfel head avatars from a short FLAME-tracked capture.\n\n"
        "Stages: ingest -> init-mesh -> phase1 -> phase2, then eval / reenact / export. "
        "Each stage reads earlier stages' outputs from the workspace WS and writes WS/<stage>/."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"sage {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
) -> None:
    """SAGE avatars from FLAME-tracked captures."""


def _register() -> None:
    from .commands import batch_cmd, config_cmd, convert_cmd, demo_cmd, eval_cmd, export_cmd, info, ingest, init_mesh, phase1, phase2, reenact_cmd, run_cmd, synth, track_cmd

    app.command("synth")(synth.synth)
    app.command("track")(track_cmd.track)
    app.command("track-models")(track_cmd.track_models)
    app.command("ingest")(ingest.ingest)
    app.command("init-mesh")(init_mesh.init_mesh)
    app.command("phase1")(phase1.phase1)
    app.command("phase2")(phase2.phase2)
    app.command("eval")(eval_cmd.eval_)
    app.command("lpips-weights")(eval_cmd.lpips_weights)
    app.command("reenact")(reenact_cmd.reenact)
    app.command("export")(export_cmd.export)
    app.command("run")(run_cmd.run)
    app.command("demo")(demo_cmd.demo)
    app.command("batch")(batch_cmd.batch)
    app.command("info")(info.info)
    app.command("config")(config_cmd.config)
    app.command("convert")(convert_cmd.convert)


_register()


def _stop_on_first_interrupt() -> None:
    """Ctrl-C raises KeyboardInterrupt once; a second one while the stage is stopping is ignored,
    so the clean-up and the "interrupted" message finish instead of ending in a traceback."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return

    def first(signum: int, frame: object) -> None:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, first)


def main() -> None:
    """Console-script entry point."""
    _stop_on_first_interrupt()
    app()


if __name__ == "__main__":
    main()
