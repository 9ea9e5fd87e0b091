"""``hfrad bench``: run the repository's benchmarks (benchmarks/run_all.py) from the CLI.

The benchmarks live in the source tree's top-level ``benchmarks/`` folder, which is not
part of the installed package: this command finds it next to ``src/`` (an editable or
source checkout) or through ``HFRAD_BENCHMARKS``, and fails with a clear message when
hfrad was installed from a wheel.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Optional

import typer

TIERS = ("quick", "large")
PARTS = ("factorize", "order", "solve", "outofcore")


def find_benchmarks() -> Path | None:
    """The repository's ``benchmarks/`` folder (with run_all.py), or None when it is not there."""
    env = os.environ.get("HFRAD_BENCHMARKS")
    candidates = [Path(env)] if env else []
    here = Path(__file__).resolve()
    # src/hfrad/cli/bench.py -> repository root is parents[3]
    candidates += [p / "benchmarks" for p in here.parents[2:5]]
    for c in candidates:
        if (c / "run_all.py").is_file():
            return c
    return None


def register(app: typer.Typer) -> None:
    @app.command()
    def bench(
        tier: str = typer.Option("quick", "--tier", help="quick (~2.5K patches) or large (10K and "
                                 "20K patches; the dense baselines hold n x n float64 matrices, 8 n^2 bytes "
                                 "each). Times of both: benchmarks/README.md."),
        only: Optional[str] = typer.Option(None, "--only", help=f"Comma list of parts: {', '.join(PARTS)}."),
    ) -> None:
        """Benchmark HF against full SVD, randomized SVD, sketching, LU and iterative solvers.

        Prints tables and writes benchmarks/results/*-TIER.json (see benchmarks/README.md).
        Form factors are computed once per scene and size and cached in benchmarks/.cache/.
        """
        if tier not in TIERS:
            raise typer.BadParameter(f"tier must be one of {', '.join(TIERS)}; got {tier!r}", param_hint="--tier")
        parts = [p.strip() for p in (only or "").split(",") if p.strip()]
        bad = [p for p in parts if p not in PARTS]
        if bad:
            raise typer.BadParameter(f"unknown part(s) {', '.join(bad)}; choose from {', '.join(PARTS)}",
                                     param_hint="--only")
        folder = find_benchmarks()
        if folder is None:
            typer.echo("hfrad bench needs the benchmarks/ folder of a source checkout, which an installed "
                       "wheel does not contain. Clone the repository and run `pip install -e .` there, "
                       "or set HFRAD_BENCHMARKS=/path/to/hfrad/benchmarks.", err=True)
            raise typer.Exit(2)
        sys.path.insert(0, str(folder))
        try:
            import run_all
        finally:
            sys.path.remove(str(folder))
        raise typer.Exit(run_all.run(tier, parts or None))
