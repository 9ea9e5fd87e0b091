"""``hfrad precompute SCENE -o FILE.hfr``: form factors + HF + Woodbury, saved for later solves."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Optional

import typer

from ..errors import InputError
from ..defaults import DEFAULT_BLOCK_SIZE
from ..resources import cores
from . import common
from .info import load_scene_from_options


def register(app: typer.Typer) -> None:
    @app.command()
    @common.scene_options
    def precompute(
        scene: str = typer.Argument(..., help="Scene file or built-in name (cornell, furnace, ...)."),
        output: Path = typer.Option(..., "-o", "--output", help="Factorization file to write (.hfr)."),
        eps: float = typer.Option(0.02, "--eps", help="Target relative Frobenius error of RF ~ Q V^T, in (0, 1)."),
        scene_options: common.SceneOptions = None,
        refine: Optional[float] = typer.Option(None, "--refine", help="After cutting, solve once on those patches and split (conforming, one level) every patch on an edge where the luminance jumps by more than this fraction of the larger side, in (0, 1) (e.g. 0.2). At most 8,000 patches before refining (the coarse solve is dense)."),
        block: Optional[int] = typer.Option(None, "--block", help=f"Column block width (patches); default min({DEFAULT_BLOCK_SIZE}, n)."),
        dtype: str = common.dtype_option("float32"),
        samples: Optional[int] = typer.Option(None, "--samples", help="Visibility rays per patch pair: 1, 4, 9, ... up to 1,024 (time grows in proportion); 0: no visibility (every pair sees each other)."),
        order: str = typer.Option("zorder", "--order", help="Internal patch order: zorder, hilbert, random, input."),
        processes: Optional[int] = typer.Option(None, "--processes", help="Form-factor worker processes, each with its own Embree scene. Default: one per core from 4,000 patches on (below, their start-up costs more than it saves), else this process; the result does not depend on it."),
        near_field: str = typer.Option("auto", "--near-field", help="Near-field split: pairs within the radius holding ~this many facing neighbours (nonzeros of a row of N) go into a sparse N, HF factors the smooth rest, the solver is Woodbury around I - D_c N (Neumann series per solve, sparse LU in the set-up). 'auto' (default): 120 where the split pays, from 20,000 (0.02 / eps)^1.5 patches on (20,000 at --eps 0.02, 5,060 at 0.05; 2,000 at least; a clustered mesh from 2,000 on, with 120 (n / 4,000)^0.75 a row from 4,000 patches, at most 400), off below; the split lowers the rank HF needs and, at equal --eps, the radiosity error; 'off' or 0: plain Woodbury."),
        far_field: str = typer.Option("auto", "--far-field", help="How the form factors of well-separated pairs are found: 'exact' (every pair), 'sampled' (each column block's near rows exactly, its far rows from a few sampled rows and skeleton columns, checked on held-out rows; a separate sample of exact rows certifies the error), 'hierarchical' (F as an H-matrix: near leaf pairs exact, far cluster pairs of low rank from a few of their rows and columns; the factors from products with it; a sample of exact rows drawn by importance certifies the error; with --scheduler or --workers the workers build the H-matrix in parts and this process factors it; the checkpoint (OUTPUT.partial, on Dask OUTPUT.partial.d/) holds the built H-matrix, so a rerun skips its build), 'auto' (default): the one measured faster, 'hierarchical' from 20,000 patches at --eps 0.05 or more on a scene that is not clustered (not on Dask), else 'exact'. 'sampled' runs on Dask too (the same leaves)."),
        scheduler: Optional[str] = typer.Option(
            None, "--scheduler", help="Run on a Dask cluster: tcp://HOST:PORT of a running `dask scheduler` "
            "(docs/cluster.md)."),
        workers: Optional[int] = typer.Option(
            None, "--workers", help="Run on a local Dask cluster of N worker processes (one thread each)."),
        quiet: bool = common.QuietOption,
    ) -> None:
        """Precompute a scene once: form factors with visibility, HF, Woodbury factors.

        Memory, n patches, b = --block, k = rank, s = 4 bytes (float32) or 8
        (float64): 40 n b (five float64 column blocks) + (2 n k + 3 k^2) s (Q, V
        and three k x k inverses) + 4 n k s (a merge), hfrad.memory.precompute_bytes;
        k is unknown before the run, so the check assumes k = min(n, 3000) and
        refuses a run above 80% of the available memory. The n x n matrix is
        never stored. Rows kept for the reciprocity copies take at most n^2 s / 4,
        a quarter of the available memory and what the estimate leaves of 80% of
        it (hfrad.formfactors.mirror.mirror_bytes); the rest wait in a scratch file
        beside OUTPUT of about n^2 s / 4 bytes less what memory holds
        (hfrad.formfactors.mirror.scratch_bytes), at most half the folder's free
        space; with less room, blocks compute the rows that do not fit and a warning
        gives the share of pairs copied. The file is unlinked as soon as it is
        created (nothing is left after an error or Ctrl-C); damaged tiles are
        detected by checksum and recomputed. With the near field (by default from 20,000 (0.02 / eps)^1.5 patches, c = 120 entries a row, up to 400 on clustered meshes of 20,000 patches; c entries a
        row): about 40 n c bytes while N is collected and, after the pass, the
        set-up: the factors, one n x k Z per distinct colour channel (3 n k s at
        most) and one channel's sparse LU while it is factored, 25 bytes an
        entry for about n c^1.5 entries (16.6 times N's entries measured on a
        clustered mesh of 60,568 patches, c = 400), plus 32 n c for N:
        hfrad.memory.near_setup_bytes, refused above 80% of the available memory.
        With --far-field sampled: no reciprocity tiles and no scratch file; besides the
        same column blocks, the certification and sampled rows' exact values (about
        (2 sqrt(n) + 400) b float64 a block) and the cluster-pair visibility table (n^2 / 1024 bytes).
        With --far-field hierarchical, instead of the column blocks and tiles: the
        H-matrix (about 12 sqrt(n) values and 2 sqrt(n) int32 a patch, 36 sqrt(n)
        values on a clustered mesh; 10.8 sqrt(n) measured at 161,808 patches, 30.2
        on the clustered Šibenik at 60,568; a value is a float32, or a 2-byte
        bfloat16 from 100,000 patches), the operator factorization (4 n l s
        for a basis of l columns, about twice the rank, plus three float64 n x 64
        product buffers), the near field's entries beside it (52 bytes each) and
        the statistics (about 2.9 KB a patch): hfrad.memory.hierarchical_bytes,
        with a rank of min(n, 256) before the run and checked again as the basis
        grows (the set-up above at that rank); the H-matrix is released before
        the set-up, and the larger of the two is refused above 80% of the
        available memory; its checkpoint, the built H-matrix, takes about 5.5
        bytes a stored float on disk (600 MB at 39,482 patches).
        A checkpoint (OUTPUT.partial) is written every 30 s, and at least 50
        times as long as its last write took apart (writes cost at most ~2% of
        the run); rerun the same command to resume after an interruption. With
        --scheduler or --workers the work runs as Dask tasks (finished subtrees
        are kept in OUTPUT.partial.d/ until the file is saved: a rerun skips
        them); the busiest worker needs hfrad.distributed.worker_bytes(n, b, k),
        about 160 MB + 2 KB n + max(25 n b, 14 n k s) + 2 n k s (docs/cluster.md).
        """
        from ..pipeline import Checkpoint, LocalBackend, PrecomputeOptions, factorize
        from ..solve.hfr import save_hfr

        t0 = time.perf_counter()
        with common.user_errors():
            common.check_dtype(dtype)
            if output.suffix != ".hfr":
                raise InputError(f"output must end in .hfr; got {output}")
            _check_options(processes=processes, samples=samples, refine=refine, scheduler=scheduler,
                           workers=workers)
            options = PrecomputeOptions(block_size=block, samples=samples)
            near = _near_field(near_field)      # a bad value is refused before the scene is read
            common.check_output(output)
            common.check_output(output.with_name(output.name + ".partial"))

            def mode(n: int, clustered: bool = False) -> str:   # what "auto" chooses (the estimate follows it)
                from ..precompute.options import far_field_mode
                return far_field_mode(far_field, n, True, eps=eps, local=scheduler is None and workers is None,
                                      clustered=clustered)

            def entries(n: int, clustered: bool = False) -> int:   # near-field entries a row, as the plan resolves them
                from ..precompute.options import near_entries
                return near_entries(near, n, eps, True, clustered=clustered, far_field=mode(n, clustered))

            def need(n: int) -> None:   # before cutting: --max-edge 1e-4 is refused at once, not by the OOM killer
                common.check_memory_for_precompute(n, min(block or DEFAULT_BLOCK_SIZE, max(n, 1)), dtype,
                                                   count="at least" if scene_options.max_edge is not None else "about",
                                                   far_field=mode(n), near_entries=entries(n))

            with common.stage_clock(quiet, start=t0) as clock:
                s = load_scene_from_options(scene, **dataclasses.asdict(scene_options), need=need, on_stage=clock)
                clock.stop()
            if refine is not None:
                clock("refine")
                from ..solve.refine import refine_by_radiosity
                before = s.n_patches
                with common.progress_bar(f"coarse solve on {before:,} patches", quiet) as bar:
                    s, marked = refine_by_radiosity(s, refine, progress=bar)
                if not quiet:
                    common.console.print(f"refined: {marked:,} of {before:,} patches marked, {s.n_patches:,} patches now")
                clock.stop()
            chosen = mode(s.n_patches, s.is_clustered)
            near_count = entries(s.n_patches, s.is_clustered)
            common.check_memory_for_precompute(s.n_patches, block or DEFAULT_BLOCK_SIZE, dtype, far_field=chosen,
                                               near_entries=near_count, clustered=s.is_clustered)
            common.warn_disk_for_hfr(output, s.n_patches, dtype)
            if not quiet and chosen == "hierarchical":
                from ..memory import human
                estimate = common.precompute_estimate(s.n_patches, 0, dtype, 'hierarchical', near_count, s.is_clustered)
                common.console.print(f"memory estimate: about {human(estimate)} for {s.n_patches:,} patches "
                                     "(rank guessed; the near field's sparse LUs included; refused above 80% of "
                                     "the available memory)", highlight=False)
            elif not quiet:
                from ..formfactors.mirror import mirror_bytes
                from ..memory import human, precompute_bytes
                itemsize = common.check_dtype(dtype).itemsize
                pass_bytes = precompute_bytes(s.n_patches, block or DEFAULT_BLOCK_SIZE, itemsize=itemsize)
                estimate = common.precompute_estimate(s.n_patches, block or DEFAULT_BLOCK_SIZE, dtype, chosen,
                                                      near_count)
                mirror = mirror_bytes(s.n_patches, itemsize, reserved=pass_bytes)
                scratch = _scratch_estimate(s.n_patches, block or DEFAULT_BLOCK_SIZE, itemsize, mirror)
                common.console.print(f"memory estimate: about {human(estimate)} for {s.n_patches:,} patches "
                                     "(rank guessed" + ("; the near field's sparse LUs included" if near_count else "")
                                     + "; refused above 80% of the available memory), plus up to "
                                     f"{human(mirror)} of form factors kept for reciprocity"
                                     + (f" and up to {human(scratch)} of them in a scratch file beside the output"
                                        if scratch else ""), highlight=False)
            if scheduler is not None or workers is not None:
                if processes not in (None, 1):
                    raise InputError("--processes is for the in-process path; with --scheduler or --workers "
                                     "the Dask workers compute the blocks")
                t_load = time.perf_counter() - t0
                clock("checks")
                clock.stop()
                parts = output.with_name(output.name + ".partial.d")   # finished subtrees: a rerun skips them
                clock("factorize on Dask")
                fac = _on_cluster(s, scheduler, workers, quiet, eps=eps, dtype=dtype, order=order,
                                  near_field=near, options=options, far_field=far_field,
                                  checkpoint=Checkpoint(parts, keep=True))
                clock("save")
                common.check_space_for_hfr(output, fac)
                save_hfr(fac, output, timings={"load": t_load, **_stage_times(fac)})
                from ..distributed import remove_checkpoint
                remove_checkpoint(parts)  # only once the .hfr is safely renamed into place
                _report(fac, output, clock)
                return
            checkpoint = output.with_name(output.name + ".partial")
            t_load = time.perf_counter() - t0
            clock("checks")
            clock.stop()
            with common.progress_bar(f"precompute {s.n_patches:,} patches", quiet) as bar:
                def status(info: dict) -> None:
                    if info.get("resumed"):    # said only once factorize has accepted the checkpoint
                        unit = info.get("resumed_unit", "column blocks were done")
                        common.console.print(f"resumed from checkpoint {checkpoint} ({info['resumed']:,} {unit})",
                                             highlight=False)
                    if "estimate" in info and not quiet:
                        line = common.estimate_line(info["estimate"], info.get("pass_over_kernel"))
                        common.console.print(line, highlight=False)
                    if bar is not None and info["blocks"]:
                        bar.note(f"rank {info['rank']:,}")

                t_fac = time.perf_counter()
                fac = factorize(s, eps, dtype=dtype, order=order, near_field=near,
                                backend=LocalBackend(processes=processes), checkpoint=Checkpoint(checkpoint, keep=True),
                                options=options, far_field=far_field, progress=bar, status=status)
                common.add_factorize_stages(clock, fac, time.perf_counter() - t_fac)
                if bar is not None:   # the factorization's rank, not the last block's (the last merges truncate)
                    bar.note(f"rank {fac.rank:,}")
            clock("save")
            common.check_space_for_hfr(output, fac)
            save_hfr(fac, output, timings={"load": t_load, **_stage_times(fac)})
            checkpoint.unlink(missing_ok=True)  # only once the .hfr is safely renamed into place
        _report(fac, output, clock)


def _check_options(*, processes, samples, refine, scheduler, workers) -> None:
    """Option values refused before any work, each in one line naming the option."""
    import re

    limit = common.MAX_PROCESSES_PER_CORE * cores()
    common.check_count(processes, "--processes", high=limit,
                       why=f"{common.MAX_PROCESSES_PER_CORE} per core at most (this machine has {cores()}); "
                           "more only add memory and start-up time")
    common.check_count(workers, "--workers", high=limit,
                       why=f"{common.MAX_PROCESSES_PER_CORE} per core at most (this machine has {cores()})")
    common.check_samples(samples)
    if refine is not None and not (0 < refine < 1):   # |L_p - L_q| / max(L_p, L_q) never reaches 1: nothing marked
        raise InputError(f"--refine threshold must be in (0, 1), a relative luminance jump |L_p - L_q| / max(L_p, L_q) "
                         f"(e.g. 0.2); got {refine}")
    if scheduler is not None:
        m = re.fullmatch(r"(?:[A-Za-z][\w+.-]*://)?(\[[0-9A-Fa-f:.]+\]|[^\s/:\[\]]+):(\d{1,5})", scheduler.strip())
        if m is None or not 1 <= int(m.group(2)) <= 65535:
            raise InputError(f"--scheduler must look like tcp://HOST:PORT (port 1-65535); got {common.quote(scheduler)}")


def _near_field(value: str) -> int | str:
    """``--near-field``: 'auto', 'off' or a number of neighbours per row."""
    if value == "auto":
        return value
    if value == "off":
        return 0
    try:
        return int(value)
    except ValueError:
        raise InputError(f"--near-field takes 'auto', 'off' or a number of neighbours per row; got {value!r}") from None


def _stage_times(fac) -> dict:
    return {k: v for k, v in fac.lowrank.info.items() if k.startswith("time")}


def _on_cluster(scene, scheduler: Optional[str], workers: Optional[int], quiet: bool, **arguments):
    """The precompute as Dask tasks (``arguments``: of :func:`hfrad.factorize`); a scheduler that cannot be
    reached exits 2 naming its address."""
    from ..distributed import SchedulerUnreachableError, WorkerLostError, connect, rank_guess, worker_bytes
    from ..pipeline import DaskBackend, factorize
    from ..memory import human

    if scheduler is not None and workers is not None:
        raise InputError("give --scheduler or --workers, not both")
    n, block = scene.n_patches, min(arguments["options"].block_size or DEFAULT_BLOCK_SIZE, scene.n_patches)
    k = rank_guess(n, arguments["eps"])
    try:
        with connect(scheduler, workers=workers) as cluster:
            where = f"{cluster.n_workers} local worker processes" if cluster.kind == "local" else \
                f"the Dask scheduler at {cluster.address} ({cluster.n_workers} workers)"
            common.console.print(
                f"running on {where}; each worker needs up to ~{human(worker_bytes(n, block, k, workers=cluster.n_workers))} "
                f"(n {n:,}, block {block}, rank ~{k:,} guessed)"
                + (f"\nDask dashboard: {cluster.dashboard}" if cluster.dashboard else ""), highlight=False)
            with common.progress_bar(f"precompute {n:,} patches on Dask", quiet) as bar:
                status = None if bar is None else (lambda info: bar.note(f"rank {info['rank']:,}"))
                fac = factorize(scene, backend=DaskBackend(scheduler=cluster), progress=bar, status=status,
                                **arguments)
                if bar is not None:   # the factorization's rank, as the summary says it
                    bar.note(f"rank {fac.rank:,}")
                return fac
    except (SchedulerUnreachableError, WorkerLostError) as exc:
        common.fail(str(exc))


def _report(fac, output: Path, clock) -> None:
    """The closing lines: the file, the error figures, and where the time went (stages adding up to the total)."""
    info = fac.lowrank.info
    clock("error figures")
    figures = common.error_figures_line(fac)
    clock.stop()
    dask = (f"; form factors {info.get('time_formfactors', 0):.1f} s and HF {info.get('time_total', 0):.1f} s summed "
            f"over {info['workers']} Dask workers" if info.get("backend") == "dask" else "")
    common.console.print(
        f"wrote {output}: {fac.n_patches:,} patches, rank {fac.rank:,}, "
        f"achieved error {fac.relative_error:.4f} (target {fac.eps})\n{figures}\n"
        f"solver {fac.solver}, time: {clock.summary()}{dask}", highlight=False)
    if info.get("hierarchical"):
        common.console.print(_hierarchical_line(info["hierarchical"]), highlight=False)
    far = info.get("far_field")
    if far:
        from ..formfactors.farfield import CERTIFICATE_FAILURE
        common.console.print(
            f"far field sampled: {far['pairs_share']:.2%} of the n^2 form factors evaluated "
            f"({far['traced_share']:.2%} with rays), {far['exact_groups']:,} of {far['groups']:,} column groups "
            f"computed exactly, {far['refined_groups']:,} refined, {far.get('split_groups', 0):,} halved; "
            f"{far.get('piece_blocks', 0):,} blocks reached HF in pieces ({far.get('dense_row_share', 0.0):.1%} of "
            f"their rows dense); its error ||G - G~||_F about "
            f"{far['error_estimate']:.3g}, upper figure {far['error_upper']:.3g} (the error above it with probability "
            f"~{CERTIFICATE_FAILURE:.1%}; {far['certificate_rows']:,} exact rows drawn in each column group: "
            "docs/method.md section 4b)", highlight=False)


def _hierarchical_line(h: dict) -> str:
    """What ``far_field="hierarchical"`` did (``info["hierarchical"]``), in words."""
    from ..formfactors.farfield import CERTIFICATE_FAILURE
    from ..memory import human

    c = h["certificate"]
    return (f"far field hierarchical: {h['pairs_share']:.2%} of the n^2 form factors evaluated "
            f"({h['exact_pairs']:,} with rays, {h['kernel_pairs']:,} kernel only), {h['blocks']:,} blocks "
            f"(mean far rank {h['mean_rank']:.1f}), {h['storage_floats'] / max(h['n'], 1):,.0f} values a patch"
            + (f" ({h.get('values', 'float32')}, {human(h['bytes'])} in all)" if "bytes" in h else "") + "; "
            f"{h['factorization']['products']:,} products; its error ||G - G_H||_F about {c['error_estimate']:.3g}, "
            f"upper figure {c['error_upper']:.3g} (the error above it with probability ~{CERTIFICATE_FAILURE:.1%}; "
            f"{c['rows']:,} exact rows drawn by importance: docs/method.md section 4c)")


def _scratch_estimate(n: int, block_size: int, itemsize: int, memory_band_bytes: int) -> int:
    """Bytes of the reciprocity scratch file when the memory band holds ``memory_band_bytes``."""
    from ..formfactors.mirror import MIRROR_LAG, band_for, scratch_bytes

    blocks = -(-n // block_size)
    near = band_for(blocks, block_size, itemsize, memory_band_bytes)
    return scratch_bytes(blocks, block_size, itemsize, near, max(blocks - MIRROR_LAG - 1, 0))
