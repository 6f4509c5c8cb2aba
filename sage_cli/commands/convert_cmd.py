"""``sage convert FILE... --trust``: rewrite old pickle-based sage files in the safe format."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .._common import cli_errors, console


def convert(
    files: Annotated[list[Path], typer.Argument(help="Old avatar (avatar.pt), SDF (sdf.pt) or checkpoint files, or folders holding them (a bundle, a workspace).")],
    trust: Annotated[bool, typer.Option("--trust", help="Required: you trust these files. Converting loads the old pickle format, which runs any code a file holds.")] = False,
    keep_backup: Annotated[bool, typer.Option("--backup/--no-backup", help="Keep each original as <name>.pickle-backup.")] = True,
) -> None:
    """Convert old pickle-based sage files (which could run code when loaded) to safetensors, in place.

    sage refuses to load the old files; run this once on files whose origin you trust. Files that
    are already in the safe format are left unchanged.
    """
    with cli_errors():
        from sage_core.errors import ConfigError, InputError
        from sage_core.serialization import convert_trusted, inspect_file

        if not trust:
            raise ConfigError("converting loads old pickle files, which can run arbitrary code: pass --trust to confirm "
                              "that you trust where these files came from")
        targets: list[Path] = []
        for f in files:
            if f.is_dir():
                found = [p for p in sorted(f.rglob("*")) if p.is_file() and p.suffix == ".pt"
                         and inspect_file(p).status == "pickle"]  # fmt: skip
                targets += found
            elif f.is_file():
                targets.append(f)
            else:
                raise InputError(f, "file or folder not found")
        if not targets:
            console.print("nothing to convert: no old pickle-based sage file found")
            return
        for p in targets:
            res = convert_trusted(p, trust=True, keep_backup=keep_backup)
            if not res.converted:
                console.print(f"{p}: already in the safe format ({res.kind or 'unknown kind'})")
            else:
                kept = f"; original kept as {res.backup.name}" if res.backup is not None else ""
                console.print(f"{p}: converted ({res.kind}){kept}")
