"""Print the latest benchmark results (benchmarks/results/*.json) as Markdown tables for the README.

Run:  python benchmarks/report.py [NAME ...]     (default: every factorize/order/solve/outofcore file)
"""

from __future__ import annotations

import json
import sys

import common

COLUMNS = {
    "factorize": ["scene", "n", "eps", "t_hf32", "t_hf64", "t_svd32", "t_svd64", "t_rsvd", "t_sketch", "k_hf32",
                  "k_opt", "k_opt@hf_err", "k_rsvd", "passes_rsvd", "k_sketch", "passes_sketch", "svd64/hf64",
                  "svd32/hf32", "svd64/hf32", "rsvd/hf32", "sketch/hf32"],
    "order": ["scene", "n", "eps", "order", "time", "time/zorder", "rank", "rank/zorder", "leaf_rank"],
    "solve": ["scene", "n", "k", "method", "batch", "time", "per_emission", "time/hf", "rel_err", "bound",
              "iterations", "bw_ratio", "gemm_frac", "modelled"],
    "outofcore": ["scene", "n", "eps", "method", "kind", "passes", "sample_size", "rank", "rel_err", "t_generate",
                  "t_compute", "total", "total/hf"],
}


def render(name: str) -> str:
    data = json.loads((common.RESULTS_DIR / f"{name}.json").read_text())
    kind = data["benchmark"]
    rows = data["summary"] if kind == "factorize" else data["rows"]
    cols = [c for c in COLUMNS[kind] if any(r.get(c) is not None for r in rows)]
    loads = [r.get("loadavg") for r in data.get("rows", []) if r.get("loadavg") is not None]
    m = data["machine"]
    head = (f"`{name}.json`: {common.machine_line(m)}, BLAS threads {m.get('blas_threads_requested')}; "
            f"load during run {min(loads):.1f}-{max(loads):.1f}" if loads else f"`{name}.json`")
    return head + "\n\n" + common.table(rows, cols, markdown=True) + "\n"


def main(argv=None) -> int:
    names = (argv if argv is not None else sys.argv[1:]) or sorted(
        p.stem for p in common.RESULTS_DIR.glob("*.json")
        if p.stem.split("-")[0] in COLUMNS and not p.stem.startswith("smoke"))
    for name in names:
        print(render(name))
    return 0


if __name__ == "__main__":
    sys.exit(main())
