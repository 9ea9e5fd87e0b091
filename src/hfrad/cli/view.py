"""``hfrad view FILE.hfr``: relight a factorization interactively in the browser."""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.markup import escape

from ..errors import InputError
from . import common


def register(app: typer.Typer) -> None:
    @app.command()
    def view(
        factorization: Path = typer.Argument(..., help="Factorization file from `hfrad precompute` (.hfr)."),
        host: str = typer.Option("127.0.0.1", "--host", help="Address to bind. The default serves this machine "
                                                             "only; 0.0.0.0 shares the page on the network "
                                                             "(anyone who has the printed URL, token included, "
                                                             "can then change the lights and save files)."),
        port: int = typer.Option(8080, "--port", min=1, max=65535,
                                 help="Port (the next free one is taken if it is busy)."),
        save_dir: Path = typer.Option(Path("."), "--save-dir", help="Folder for the page's saved PNGs and "
                                                                   "emission files (also sent to the browser)."),
        direct: bool = typer.Option(False, "--direct", help="Re-solve fac.solve(E) on every change instead of "
                                                            "summing batched unit solutions (for comparison)."),
    ) -> None:
        """Serve a web page to relight FILE.hfr: per-emitter on/off, intensity and colour, exposure,
        false colour, live solve timings; save PNG and emission JSON.

        The page is locked to its printed URL, which carries a random token
        (http://127.0.0.1:8080/?token=...): requests without it, websockets
        opened by other sites' pages and requests under another host name are refused.

        Memory: the factors (Q, V and three k x k inverses: (2 n k + 3 k^2) x 4
        bytes in float32) plus one radiosity per emitter.
        """
        from ..viewer.guard import check_bindable, is_loopback

        with common.user_errors():
            host = host.strip()
            if host.startswith("[") and host.endswith("]"):
                host = host[1:-1]
            check_bindable(host, port)             # before loading: a wrong --host or a full port range fails at once
            from ..viewer import ViewerApp
            if factorization.suffix.lower() != ".hfr":
                raise InputError(f"{factorization}: not a factorization file (.hfr); make one with "
                                 "`hfrad precompute SCENE -o FILE.hfr`")
            if not factorization.is_file():
                raise FileNotFoundError(f"{factorization}: no such file")
            if not save_dir.is_dir():
                raise InputError(f"--save-dir {save_dir}: no such folder")
            fac = common.load_factorization(factorization)
            viewer = ViewerApp(fac, host=host, port=port, save_dir=save_dir, direct=direct)
        if is_loopback(host):
            where = "this machine only; --host 0.0.0.0 shares it on the network"
        else:
            where = "reachable from the network"
            common.console.print(f"[yellow]warning:[/] --host {escape(host)} is not a loopback address: other "
                                 "machines can reach the page; anyone with its URL (token included) can change "
                                 "the lights and write files to --save-dir", highlight=False)
        common.console.print(f"hfrad view: {viewer.url}  (bound to {host}: {where}); "
                             f"{fac.n_patches:,} patches, rank {fac.rank:,}. Ctrl+C stops.",
                             highlight=False, markup=False)
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass
        finally:
            viewer.close()
