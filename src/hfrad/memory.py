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


#: Floats an H-matrix of F holds a patch (dense near blocks and low-rank far blocks,
#: :mod:`hfrad.formfactors.hmatrix`), over sqrt(n): they grow with n (the exact blocks' rows). Measured
#: on the Cornell box, eps 0.05 (leaf 32, block tolerance 0.01): 359 a patch at 394 patches, 861 at
#: 1,508, 2,310 at 9,986 (18, 22 and 23 sqrt(n)); taken a little above until measured at scale.
HMATRIX_FLOATS_PER_SQRT_N = 24
#: The same on a clustered mesh (patches made of triangles; more mixed pairs and shadow-edge rows):
#: 35.4 measured on the Šibenik cathedral at 60,568 patches (527 million floats).
HMATRIX_FLOATS_PER_SQRT_N_CLUSTERED = 36
#: Bytes a patch of what ``far_field="hierarchical"`` holds besides the H-matrix and the factors: the
#: pass statistics' sampled rows (at most ~300 float32 a patch), their products and sketch, and the
#: float64 product buffers of 70 vectors (three copies).
HIERARCHICAL_STATS_BYTES = 4 * 300 + 8 * 3 * 70
#: Columns the operator factorization adds to its basis at a time (:func:`hfrad.lowrank.operator_factorization`).
OPERATOR_BLOCK = 64


def hierarchical_bytes(n: int, rank_guess_: int | None = None, itemsize: int = 4, clustered: bool = False) -> int:
    """Rough peak memory of ``factorize(far_field="hierarchical")``, bytes.

    The H-matrix (``HMATRIX_FLOATS_PER_SQRT_N * sqrt(n)`` float32 a patch, or
    ``HMATRIX_FLOATS_PER_SQRT_N_CLUSTERED`` on a ``clustered`` mesh), the operator factorization at its
    SVD (basis P and projection B, l x n each, B's right singular vectors, the two n x k factors:
    ``5 n k s`` with l = k, plus a block of ``OPERATOR_BLOCK`` vectors in float64, three copies in the
    products) and the pass statistics (``HIERARCHICAL_STATS_BYTES`` a patch). The rank k is
    :func:`rank_guess` unless given (see :data:`RANK_ASSUMPTION`).
    """
    k = rank_guess(n) if rank_guess_ is None else rank_guess_
    per_sqrt_n = HMATRIX_FLOATS_PER_SQRT_N_CLUSTERED if clustered else HMATRIX_FLOATS_PER_SQRT_N
    return int(n * (4 * per_sqrt_n * n ** 0.5 + 5 * k * itemsize + 3 * 8 * OPERATOR_BLOCK
                    + HIERARCHICAL_STATS_BYTES))


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
                          itemsize: int = 4, clustered: bool = False) -> int:
    """Rough peak memory of a precompute in this process, bytes: the larger of its pass over F
    (:func:`precompute_bytes`, or :func:`hierarchical_bytes` with ``far_field="hierarchical"``) and the
    solver's set-up (:func:`near_setup_bytes`, with ``near_entries`` c > 0 a row of N): the pass's
    blocks (or the H-matrix) are released before the set-up, and the near field's LUs are factored
    beside the pass only where they fit (:mod:`hfrad.solve.prefetch`). ``clustered``: a clustered mesh
    (:func:`hierarchical_bytes`)."""
    if far_field == "hierarchical":
        pass_bytes = hierarchical_bytes(n, itemsize=itemsize, clustered=clustered)
    else:
        pass_bytes = precompute_bytes(n, block_size, itemsize=itemsize)
    return max(pass_bytes, near_setup_bytes(n, near_entries, itemsize=itemsize))
