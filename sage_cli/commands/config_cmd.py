"""``sage config STAGE``: print a stage's resolved configuration (preset < regime < file < --set) with help."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from .._common import ConfigOpt, PresetOpt, SetOpt, cli_errors, console, parse_sets, resolve_stage_config


def config(
    stage: Annotated[str, typer.Argument(help="Stage name: ingest, init-mesh, phase1, ...")],
    preset: PresetOpt = "default",
    config: ConfigOpt = None,
    set_: SetOpt = None,
    explain: Annotated[bool, typer.Option("--explain", help="List every field (dotted names of nested sections) with its value, allowed values or range and help text instead of YAML.")] = False,
    regime: Annotated[Optional[str], typer.Option("--regime", help="Apply a regime's defaults (mv-sf, mv-mf, sv-hr, one-shot), as a workspace ingested with it does.")] = None,
) -> None:
    """Print the configuration a stage would run with, as YAML (usable as a --config file)."""
    with cli_errors():
        import yaml

        from sage_core.config import STAGE_CONFIGS, describe, describe_allowed, legacy_aliases, section_name, to_dict
        from sage_core.errors import ConfigError

        if stage not in STAGE_CONFIGS:
            raise ConfigError(f"unknown stage '{stage}' (stages with a config: {', '.join(STAGE_CONFIGS)})")
        if regime is not None:
            from sage_core.data.ingest import REGIMES

            if regime not in REGIMES:
                raise ConfigError(f"unknown regime '{regime}' (regimes: {', '.join(REGIMES)})")
        cfg = resolve_stage_config(stage, preset, config, parse_sets(set_), regime=regime)
        if explain:
            from rich.table import Table

            t = Table(title=f"{stage} ({preset} preset)")
            t.add_column("option", no_wrap=True)
            t.add_column("value")
            t.add_column("allowed")
            t.add_column("meaning")
            allowed = describe_allowed(type(cfg))
            former = {new: old for old, new in legacy_aliases(type(cfg)).items()}
            for name, help_text, _ in describe(type(cfg)):
                obj = cfg
                for part in name.split("."):
                    obj = getattr(obj, part)
                if name in former:
                    help_text += f" (flat name {former[name]})"
                t.add_row(name, str(obj), allowed.get(name, ""), help_text)
            console.print(t)
            return
        typer.echo(yaml.safe_dump({section_name(stage): to_dict(cfg)}, sort_keys=False).rstrip())
