"""Command groups whose commands import their modules when they run, so that a start costs what
its command needs (the console script's root, `depthstation evaluate`)."""

from __future__ import annotations

import importlib
from typing import Any

import typer
from typer.core import TyperGroup


def lazy_group(commands: dict[str, str], helps: dict[str, str] | None = None) -> type[TyperGroup]:
    """A typer group class (`typer.Typer(cls=...)`) whose commands come from `commands`, in that
    order: name -> "module:attribute", the attribute being the command's function, a sub-app (a
    Typer, its help from `helps`) or `register` (a function that adds commands to an app). A
    command's module is imported the first time the command is asked for; `--help` lists them all,
    so it loads them all. The caller names the modules under `TYPE_CHECKING`, so that the import
    graph the layer check and mypy read holds them."""

    class LazyGroup(TyperGroup):
        # typer >= 0.22 types these with its own copy of click, older typer with click's
        def list_commands(self, ctx: Any) -> list[str]:
            return [*commands, *(n for n in super().list_commands(ctx) if n not in commands)]

        def get_command(self, ctx: Any, cmd_name: str) -> Any:
            if cmd_name not in self.commands and cmd_name in commands:
                for name, command in _load(cmd_name, commands[cmd_name], helps or {}).items():
                    self.commands.setdefault(name, command)
            return super().get_command(ctx, cmd_name)

    return LazyGroup


def _load(name: str, target: str, helps: dict[str, str]) -> dict[str, Any]:
    """The commands `target` ("module:attribute") gives a group, by name."""
    module, _, attr = target.partition(":")
    obj = getattr(importlib.import_module(module), attr)
    part = typer.Typer()
    if isinstance(obj, typer.Typer):
        part.add_typer(obj, name=name, help=helps.get(name))
    elif attr == "register":
        obj(part)
    else:
        part.command(name)(obj)
    return dict(typer.main.get_group(part).commands)
