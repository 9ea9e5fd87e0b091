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
    from . import bench, daylight, demo, design, formfactors, info, lux, precompute, render, solve, view

    for module in (demo, info, formfactors, precompute, solve, render, design, lux, daylight, view, bench):
        module.register(app)


_register_commands()


#: Seconds before an interrupt swallowed by a finalizer is raised again (the finalizer has returned by then).
REDELIVER_DELAY = 0.01


def redeliver_interrupts() -> None:
    """Make a Ctrl-C that lands in a finalizer stop the command all the same.

    Python raises KeyboardInterrupt wherever the main thread is when SIGINT
    arrives; inside a finalizer (``__del__``, a weakref or ``gc`` callback,
    which the garbage collector runs between any two lines) the interpreter
    reports it through :data:`sys.unraisablehook` as "Exception ignored" and
    goes on, so the command kept running. This hook catches such an interrupt
    and has it delivered again as SIGINT (``_thread.interrupt_main``) from a
    timer thread :data:`REDELIVER_DELAY` seconds later, once the finalizer has
    returned; the SIGINT handler installed here raises KeyboardInterrupt as the
    default one does, except inside the hook itself, where it schedules one
    more try. Every other unraisable exception goes to the previous hook.
    """
    import _thread
    import signal
    import sys
    import threading

    previous = sys.unraisablehook

    def later() -> None:
        timer = threading.Timer(REDELIVER_DELAY, _thread.interrupt_main)
        timer.daemon = True
        timer.start()

    def hook(unraisable) -> None:
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
            later()
            return
        previous(unraisable)

    def on_sigint(signum, frame) -> None:
        while frame is not None:
            if frame.f_code is hook.__code__:   # raised here it would be swallowed again
                later()
                return
            frame = frame.f_back
        raise KeyboardInterrupt

    sys.unraisablehook = hook
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:   # not if SIGINT is ignored
        signal.signal(signal.SIGINT, on_sigint)


def main() -> None:
    """Entry point of the ``hfrad`` console script."""
    redeliver_interrupts()
    app()
