"""The command-line options several commands share, declared once (typer annotations).

pipeline/cli.py and the commands that live beside their packages (evaluation/commands.py,
viewer/command.py) import them from here: a leaf module, so no command imports the CLI.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

SceneArg = Annotated[Path, typer.Argument(help="Scene folder holding scene.json.", show_default=False)]
OutOpt = Annotated[Optional[Path], typer.Option("--out", help="Run folder (default: runs/<scene-name>/).")]
ConfigOpt = Annotated[
    Optional[Path], typer.Option("--config", help="YAML or JSON file of stage parameters: {stage: {param: value}}.")
]
SetOpt = Annotated[
    Optional[list[str]], typer.Option("--set", help="Override one parameter: STAGE.PARAM=VALUE (repeatable).")
]
