"""Memory checks: refuse with a clear message rather than swap the machine to death."""

from __future__ import annotations

from .errors import MemoryLimitError


def available_bytes() -> int:
    """Memory available to new allocations (Linux MemAvailable; a large number elsewhere)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:  # pragma: no cover - non-Linux
        pass
    return 1 << 62


def _address_space_left() -> int:
    """Bytes the process may still map under its address-space limit (``ulimit -v``); large if none."""
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft == resource.RLIM_INFINITY:
            return 1 << 62
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmSize:"):
                    return max(0, soft - int(line.split()[1]) * 1024)
    except (ImportError, OSError, ValueError):  # pragma: no cover - non-Linux
        pass
    return 1 << 62


def release_freed_memory() -> None:
    """Hand the memory this process has freed back to the system (glibc's ``malloc_trim``; nothing
    elsewhere), at the end of a stage that freed much of what it allocated.

    Arrays of a few megabytes come from the heap (glibc raises its mmap threshold to 32 MB as large
    blocks are freed) and the H-matrix build frees many on its threads' arenas, which glibc keeps:
    at 161,808 Cornell-box patches the process held 6.4 GiB at the end of the build, 4.1 GiB after a
    trim (39,482 patches: 1.09 and 0.78 GiB), and the operator factorization and the near field's
    LUs then came on top of the 6.4. Later stages may reuse that memory, but not the near LUs of
    another thread or the set-up's large arrays, so it counted at the run's peak.
    """
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        pass


def human(nbytes: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if nbytes < 1024 or unit == "TB":
            return f"{nbytes:.1f} {unit}"
        nbytes /= 1024
    return f"{nbytes:.1f} TB"  # pragma: no cover


def require(nbytes: float, what: str, hint: str = "", fraction: float = 0.8) -> None:
    """Raise MemoryLimitError if ``nbytes`` exceeds ``fraction`` of the available memory."""
    limit = fraction * min(available_bytes(), _address_space_left())
    if nbytes > limit:
        raise MemoryLimitError(f"{what} needs about {human(nbytes)} but only {human(limit)} is available"
                               + (f"; {hint}" if hint else ""))


#: The rank is only known after the run; the memory check assumes this much.
RANK_ASSUMPTION = ("min(n, 3000); the true rank grows with n and 1/eps and is larger for some scenes "
                   "(hfrad.distributed.rank_guess: ~19 sqrt(n) at eps 0.02 on the Cornell box)")


def rank_guess(n: int) -> int:
    """The rank the memory check assumes before a run (see :data:`RANK_ASSUMPTION`)."""
    return min(n, 3000)


def factors_bytes(n: int, k: int, itemsize: int = 4) -> int:
    """Memory of a factorization ready to solve: Q and V (2 n k values of ``itemsize``
    bytes) and three k x k inverses in the same dtype (:class:`~hfrad.solve.woodbury.HFactorization`)."""
    return (2 * n * k + 3 * k * k) * itemsize


def precompute_bytes(n: int, block_size: int, rank_guess_: int | None = None, itemsize: int = 4) -> int:
    """Rough peak memory of ``factorize``, bytes: ``40 n b + (2 n k + 3 k^2) s + 4 n k s``.

    Five float64 n x b column blocks (b = ``block_size``: the one being factorized, the next one
    handed over, and in the form-factor pipeline the one whose last rays are cast, the one whose
    rays are queued and the kernel of the one after), the factors
    (:func:`factors_bytes`, s = ``itemsize``) and a merge, which holds about
    twice the rank transiently (4 n k values). The rank k is not known before
    the run: :func:`rank_guess` (:data:`RANK_ASSUMPTION`) unless given.
    """
    k = rank_guess(n) if rank_guess_ is None else rank_guess_
    return 5 * 8 * n * block_size + factors_bytes(n, k, itemsize) + 4 * n * k * itemsize


#: Floats an H-matrix of F holds a patch (dense near blocks and shadow-edge rows, low-rank far blocks,
#: :mod:`hfrad.formfactors.hmatrix`), over sqrt(n): they grow with n (the exact blocks' rows). Measured
#: on the Cornell box, eps 0.05 (leaf 32, block tolerance 0.01), all-zero rows and columns dropped:
#: 11.6 sqrt(n) at 39,482 patches, 10.8 at 161,808 and 10.3 at 296,350 (2026-12-07, AMD EPYC VM).
HMATRIX_FLOATS_PER_SQRT_N = 12
#: The same on a clustered mesh (patches made of triangles; more mixed pairs and shadow-edge rows), measured
#: on the Šibenik cathedral with the zeros dropped: 21.0 sqrt(n) at 10,181 patches, 23.8 at 20,616 and 30.2
#: at 60,568 (450 million floats; 35.4 before the zeros were dropped). It still grows: kept at 36.
HMATRIX_FLOATS_PER_SQRT_N_CLUSTERED = 36
#: Row numbers (int32) the H-matrix's blocks keep a patch, over sqrt(n): 1.29 at 39,482 Cornell-box
#: patches, 1.50 at 161,808.
HMATRIX_ROWS_PER_SQRT_N = 2
#: Bytes a patch of what ``far_field="hierarchical"`` holds besides the H-matrix and the factors: the
#: pass statistics' sampled rows (at most ~300 float32 a patch), their products and sketch, and the
#: float64 product buffers of 70 vectors (three copies).
HIERARCHICAL_STATS_BYTES = 4 * 300 + 8 * 3 * 70
#: Columns the operator factorization adds to its basis at a time (:func:`hfrad.lowrank.operator_factorization`).
OPERATOR_BLOCK = 64
#: The rank ``far_field="hierarchical"``'s check assumes before the run; the operator factorization checks
#: again as its basis grows (:func:`operator_bytes`), so a larger rank is refused when it is reached.
HIERARCHICAL_RANK_ASSUMPTION = ("min(n, 256) before the run (measured at eps 0.05: 149-193 on the Cornell box "
                                "from 39,482 to 296,350 patches and 268 at 496,176, 12-59 on the Šibenik "
                                "cathedral; at eps 0.02: 1,882 on the Cornell box at 39,482 patches), checked "
                                "again as the basis grows")


def hierarchical_rank_guess(n: int) -> int:
    """The rank the hierarchical path's check assumes before a run (:data:`HIERARCHICAL_RANK_ASSUMPTION`)."""
    return min(n, 256)


def hmatrix_bytes(n: int, clustered: bool = False, value_bytes: int = 4) -> int:
    """An H-matrix of n patches, bytes: ``(v c + 4 x 2) sqrt(n)`` a patch (c sqrt(n) values of ``value_bytes``
    v each, 4 for float32 and 2 for bfloat16, and :data:`HMATRIX_ROWS_PER_SQRT_N` sqrt(n) int32 row numbers),
    c :data:`HMATRIX_FLOATS_PER_SQRT_N` (``clustered``: :data:`HMATRIX_FLOATS_PER_SQRT_N_CLUSTERED`)."""
    per_sqrt_n = HMATRIX_FLOATS_PER_SQRT_N_CLUSTERED if clustered else HMATRIX_FLOATS_PER_SQRT_N
    return int(n * n ** 0.5 * (value_bytes * per_sqrt_n + 4 * HMATRIX_ROWS_PER_SQRT_N))


def operator_bytes(n: int, basis: int, itemsize: int = 4) -> int:
    """The operator factorization with a basis of ``basis`` columns, bytes: P and B (``2 l n s``), the
    factors Q and V it ends with (at most ``2 l n s`` more), ``OPERATOR_BLOCK`` vectors in float64 (three
    copies in the products) and the pass statistics (``HIERARCHICAL_STATS_BYTES`` a patch)."""
    return int(n * (4 * basis * itemsize + 3 * 8 * OPERATOR_BLOCK + HIERARCHICAL_STATS_BYTES))


#: Bytes an entry of the near field takes while the operator factorization runs beside the H-matrix: its
#: coordinates (row, column, value: 24) and, for an entry taken out of a low-rank block, the products'
#: sparse correction and its squares (two float32 CSRs and a float64 one: 28 more). The upper figure, all
#: entries from low-rank blocks; measured with tracemalloc at 39,482 Cornell-box patches (58% of 5.8M
#: entries from low-rank blocks): 41.8 (65.8 while the precompute also kept the coordinates take_near
#: returned, until 2026-12-08; 63 measured by RSS at 296,350 patches then).
NEAR_TAKEN_BYTES = 52


def hierarchical_bytes(n: int, rank_guess_: int | None = None, itemsize: int = 4, clustered: bool = False,
                       near_entries: int = 0, value_bytes: int = 4) -> int:
    """Rough peak memory of ``factorize(far_field="hierarchical")`` up to its solver set-up, bytes: the
    H-matrix (:func:`hmatrix_bytes`, its values ``value_bytes`` each), the near field's ``near_entries`` a
    row taken out of it (:data:`NEAR_TAKEN_BYTES` an entry) and the operator factorization beside them
    (:func:`operator_bytes`) with a basis of twice the rank (measured: 384 columns for rank 163, 448
    for 193), the rank :func:`hierarchical_rank_guess` unless given (see
    :data:`HIERARCHICAL_RANK_ASSUMPTION`).
    """
    k = hierarchical_rank_guess(n) if rank_guess_ is None else rank_guess_
    return (hmatrix_bytes(n, clustered, value_bytes) + NEAR_TAKEN_BYTES * n * near_entries
            + operator_bytes(n, 2 * k, itemsize))


#: Entries a row of the near field's sparse LU (SuperLU, minimum degree on A^T + A) over ``c^1.5``, c the
#: entries a row of N: it grows faster than N. Measured (N's pattern, one channel): the Cornell box,
#: c = 120, 0.70 at 9,986 patches and 0.53 at 39,482; the Šibenik cathedral, clustered, 0.69 at 10,181
#: patches (c = 242), 0.67 at 20,616 and 0.84 at 60,568 (c = 400: 396 million entries, 16.6 times N's).
#: Taken as 1: an upper figure on both scenes.
NEAR_LU_ENTRIES_PER_C15 = 1.0
#: Bytes an LU entry takes while one channel is factored: SuperLU's own storage (about 9), SciPy's float64
#: copy of L and U (12) and the panel solver's float32 copy (4); measured 24.7 (Šibenik, 10,181 patches)
#: and 25.0. Held afterwards, per channel: about 8 (float32 values and int32 indices).
NEAR_LU_PEAK_BYTES = 25
#: Bytes an entry of N takes while the set-up holds it: two float64 CSR copies (the assembly's and the
#: solver's) and the sweeps' float32 copy.
NEAR_N_BYTES = 2 * 12 + 8


#: The solver's set-up factors ``I - D_c N`` (sparse LU) only up to this many entries a row of N; above,
#: it sweeps the Neumann series instead (:func:`hfrad.solve.nearfield.near_setup_runner`): the LU's fill
#: grows with the entries (16.6 times N's at c = 400), the sweeps' work only with N. Šibenik, clustered,
#: 10,181 patches, c = 242, rank 31, one channel (machine loaded by another run): LU 4.1 s and its solves
#: 0.2 s, against 0.6 s of sweeps (18, spectral bound 0.665), Z apart 4.5e-6.
NEAR_LU_MOST_ENTRIES = 200
#: Bytes a patch and column the set-up's Neumann sweeps hold (float64 right-hand sides, iterate,
#: previous iterate and the result: four n x w arrays), for panels of at most ``NEUMANN_COLUMNS`` columns.
NEUMANN_BYTES = 4 * 8
#: Columns a panel of the set-up's Neumann sweeps takes in this process (:class:`hfrad.solve.nearfield.InProcess`).
NEUMANN_COLUMNS = 64


def near_lu_entries(n: int, entries: int) -> float:
    """Entries of one channel's sparse LU of ``I - D_c N``, estimated (:data:`NEAR_LU_ENTRIES_PER_C15`)."""
    return NEAR_LU_ENTRIES_PER_C15 * n * float(entries) ** 1.5


def near_lu_bytes(n: int, entries: int) -> int:
    """One channel's sparse LU while it is factored, bytes: ``25 n c^1.5`` (:data:`NEAR_LU_PEAK_BYTES` an
    entry of :func:`near_lu_entries`; the channels are factored one at a time)."""
    return int(NEAR_LU_PEAK_BYTES * near_lu_entries(n, entries)) if entries else 0


def near_factored(entries: int) -> bool:
    """Whether the set-up factors a near field of ``entries`` a row (:data:`NEAR_LU_MOST_ENTRIES`)."""
    return 0 < entries <= NEAR_LU_MOST_ENTRIES


def near_field_bytes(n: int, entries: int) -> int:
    """Peak of the near field's own set-up, bytes: ``25 n c^1.5 + 32 n c`` for c entries a row of N.

    One channel's sparse LU while it is factored (:func:`near_lu_bytes`; none above
    :data:`NEAR_LU_MOST_ENTRIES` entries a row, where the set-up sweeps) and N itself
    (:data:`NEAR_N_BYTES` an entry). 0 without the near field (``entries`` 0).
    """
    if not entries:
        return 0
    return (near_lu_bytes(n, entries) if near_factored(entries) else 0) + NEAR_N_BYTES * n * entries


def near_setup_bytes(n: int, entries: int, rank_guess_: int | None = None, itemsize: int = 4) -> int:
    """Peak of the solver's set-up with the near field, bytes: the factors (:func:`factors_bytes`), three
    n x k ``Z_c`` (one a distinct colour channel, ``3 n k s``), :func:`near_field_bytes` and, where the
    set-up sweeps instead of factoring, the sweeps' ``32 n min(k, 64)`` (:data:`NEUMANN_BYTES`). The rank
    k is :func:`rank_guess` unless given (see :data:`RANK_ASSUMPTION`)."""
    if not entries:
        return 0
    k = rank_guess(n) if rank_guess_ is None else rank_guess_
    sweeps = 0 if near_factored(entries) else NEUMANN_BYTES * n * min(k, NEUMANN_COLUMNS)
    return factors_bytes(n, k, itemsize) + 3 * n * k * itemsize + near_field_bytes(n, entries) + sweeps


def precompute_peak_bytes(n: int, block_size: int, *, far_field: str = "exact", near_entries: int = 0,
                          itemsize: int = 4, clustered: bool = False, hmatrix_value_bytes: int = 4) -> int:
    """Rough peak memory of a precompute in this process, bytes: the larger of its pass over F
    (:func:`precompute_bytes`, or :func:`hierarchical_bytes` with ``far_field="hierarchical"``) and the
    solver's set-up (:func:`near_setup_bytes`, with ``near_entries`` c > 0 a row of N): the pass's
    blocks (or the H-matrix) are released before the set-up, and the near field's LUs are factored
    beside the pass only where they fit (:mod:`hfrad.solve.prefetch`). ``clustered``: a clustered mesh,
    ``hmatrix_value_bytes``: 4 or 2 (bfloat16) a value of the H-matrix (:func:`hierarchical_bytes`). The
    hierarchical path assumes :func:`hierarchical_rank_guess` for both and checks again as its basis grows
    (:func:`hfrad.precompute.hierarchical.basis_guard`); the column pass assumes :func:`rank_guess`."""
    if far_field == "hierarchical":
        k = hierarchical_rank_guess(n)
        return max(hierarchical_bytes(n, k, itemsize=itemsize, clustered=clustered, near_entries=near_entries,
                                      value_bytes=hmatrix_value_bytes),
                   near_setup_bytes(n, near_entries, k, itemsize=itemsize))
    return max(precompute_bytes(n, block_size, itemsize=itemsize), near_setup_bytes(n, near_entries, itemsize=itemsize))
