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
#: Bytes a patch of what ``far_field="hierarchical"`` holds besides the H-matrix and the factors: the
#: pass statistics' sampled rows (at most ~300 float32 a patch), their products and sketch, and the
#: float64 product buffers of 70 vectors (three copies).
HIERARCHICAL_STATS_BYTES = 4 * 300 + 8 * 3 * 70
#: Columns the operator factorization adds to its basis at a time (:func:`hfrad.lowrank.operator_factorization`).
OPERATOR_BLOCK = 64


def hierarchical_bytes(n: int, rank_guess_: int | None = None, itemsize: int = 4) -> int:
    """Rough peak memory of ``factorize(far_field="hierarchical")``, bytes.

    The H-matrix (``HMATRIX_FLOATS_PER_SQRT_N * sqrt(n)`` float32 a patch), the operator factorization at its
    SVD (basis P and projection B, l x n each, B's right singular vectors, the two n x k factors:
    ``5 n k s`` with l = k, plus a block of ``OPERATOR_BLOCK`` vectors in float64, three copies in the
    products) and the pass statistics (``HIERARCHICAL_STATS_BYTES`` a patch). The rank k is
    :func:`rank_guess` unless given (see :data:`RANK_ASSUMPTION`).
    """
    k = rank_guess(n) if rank_guess_ is None else rank_guess_
    return int(n * (4 * HMATRIX_FLOATS_PER_SQRT_N * n ** 0.5 + 5 * k * itemsize + 3 * 8 * OPERATOR_BLOCK
                    + HIERARCHICAL_STATS_BYTES))
