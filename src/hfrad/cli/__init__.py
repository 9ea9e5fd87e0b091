"""The ``hfrad`` command line: one module per command, each with ``register(app)``."""

from __future__ import annotations

import typer

app = typer.Typer(
    name="hfrad",
    help="Radiosity with infinite bounces: precompute a scene once, re-light it in milliseconds.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback(invoke_without_command=True)
def _root(
    ctx: typer.Context,
    version: bool = typer.Option(False, "--version", help="Print the version and exit.", is_eager=True),
) -> None:
    """Radiosity with infinite bounces: precompute a scene once, re-light it in milliseconds."""
    from .common import show_warnings_plainly

    show_warnings_plainly()
    if version:
        from .._version import __version__

        typer.echo(f"hfrad {__version__}")
        raise typer.Exit()
    if ctx.invoked_subcommand is None:
        typer.echo(ctx.get_help())


def _register_commands() -> None:
    from . import bench, demo, design, formfactors, info, lux, precompute, render, solve, view

    for module in (demo, info, formfactors, precompute, solve, render, design, lux, view, bench):
        module.register(app)


_register_commands()


def main() -> None:
    """Entry point of the ``hfrad`` console script."""
    app()
