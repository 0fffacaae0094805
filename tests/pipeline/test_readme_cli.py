"""The README's CLI reference and `pano-pipe --help` list the same commands and options."""

from __future__ import annotations

import re
from pathlib import Path

import typer

from pipeline.cli import app

README = Path(__file__).resolve().parents[2] / "README.md"


def cli_commands() -> dict:
    root = typer.main.get_command(app)
    out = {}
    for name, cmd in root.commands.items():
        if hasattr(cmd, "commands"):  # a group (typer may ship its own click)
            for sub, subcmd in cmd.commands.items():
                out[f"{name} {sub}"] = subcmd
        else:
            out[name] = cmd
    return out


def reference_rows() -> list[str]:
    text = README.read_text()
    section = text.split("## CLI reference", 1)[1].split("\n## ", 1)[0]
    return [line for line in section.splitlines() if line.startswith("| ")]


def test_every_command_is_in_the_readme_and_every_readme_command_exists():
    groups = {name.split()[0] for name in cli_commands() if " " in name}  # bench, models
    documented = set()
    for row in reference_rows():
        m = re.match(r"\| `pano-pipe ([a-z-]+)(?: ([a-z-]+))?", row)
        if m:
            documented.add(f"{m.group(1)} {m.group(2)}" if m.group(1) in groups else m.group(1))
    assert documented == set(cli_commands())


def test_options_in_the_readme_exist_on_run_and_bench():
    commands = cli_commands()
    run_opts = {o for p in commands["run"].params for o in getattr(p, "opts", [])}
    bench_opts = {o for p in commands["bench batch"].params for o in getattr(p, "opts", [])}
    for row in reference_rows():
        m = re.match(r"\| &nbsp;&nbsp;`(--[a-z-]+)", row)
        if m:
            assert m.group(1) in run_opts | bench_opts, m.group(1)
