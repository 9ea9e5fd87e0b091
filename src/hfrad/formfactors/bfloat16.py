"""Form-factor values held in 16 bits: bfloat16, the upper half of a float32.

A bfloat16 keeps float32's 8-bit exponent and the top 7 bits of its mantissa, so a form factor
of any size (1e-12 or 0.4) is held to a relative rounding error of at most 2^-8 (0.39%, round to
nearest even; 0.17% root mean square) and decoded by a shift: no scale a block, no underflow.
IEEE half precision would keep 3 more mantissa bits but flushes form factors below 6e-5 to
subnormals (a million patches put most far pairs at 1e-7 to 1e-9), and numba has no float16 on
the CPU.

The H-matrix (:mod:`hfrad.formfactors.hmatrix`) holds its values this way where memory is what
limits the scene size (``values`` of :class:`~hfrad.formfactors.hmatrix.HMatrixOptions`): half the
bytes of its dense entries and low-rank factors. Its block kernels read a value with
:func:`stored_value`, which is the plain read for a float32 array and the decode for a uint16
(bfloat16) one, chosen when numba compiles the kernel for the array's type.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic, overload

__all__ = ["VALUE_DTYPES", "to_bfloat16", "from_bfloat16", "stored_value", "value_dtype", "ROUNDING"]

#: What a value array may hold: float32 (exact as computed) or bfloat16 bits in a uint16 array.
VALUE_DTYPES = {"float32": np.dtype(np.float32), "bfloat16": np.dtype(np.uint16)}
#: The largest relative rounding error of a bfloat16 value (round to nearest even): half the spacing of
#: 8 significant bits at the bottom of a binade, 2^-8.
ROUNDING = 2.0 ** -8
#: Values converted a slab at a time (the uint32 work arrays of a multi-GB array stay small).
_SLAB = 1 << 22


def value_dtype(values: str) -> np.dtype:
    """The array dtype that holds values of kind ``values`` ("float32" or "bfloat16")."""
    try:
        return VALUE_DTYPES[values]
    except KeyError:
        raise ValueError(f"values must be one of {', '.join(map(repr, VALUE_DTYPES))}; got {values!r}") from None


def to_bfloat16(x: np.ndarray) -> np.ndarray:
    """float32 values -> uint16 bfloat16 bits, rounded to nearest (ties to even); same shape.

    ``x`` is converted to float32 first. Finite inputs only (form factors and their factors)."""
    x = np.ascontiguousarray(x, np.float32)
    flat, out = x.reshape(-1), np.empty(x.size, np.uint16)
    for at in range(0, flat.size, _SLAB):
        u = flat[at:at + _SLAB].view(np.uint32)
        # adding 0x7FFF plus the kept part's lowest bit rounds the dropped half to nearest, ties to even
        out[at:at + _SLAB] = (u + (np.uint32(0x7FFF) + ((u >> np.uint32(16)) & np.uint32(1)))) >> np.uint32(16)
    return out.reshape(x.shape)


def from_bfloat16(bits: np.ndarray) -> np.ndarray:
    """uint16 bfloat16 bits -> float32 values (exact); same shape."""
    bits = np.ascontiguousarray(bits, np.uint16)
    return (bits.astype(np.uint32) << np.uint32(16)).view(np.float32)


@intrinsic
def _float32_from_bits(typingctx, bits):
    """The float32 whose IEEE bits are the low 32 bits of the integer ``bits`` (a bit cast, no conversion)."""
    if not isinstance(bits, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        low = args[0]
        if bits.bitwidth > 32:
            low = builder.trunc(low, ir.IntType(32))
        return builder.bitcast(low, ir.FloatType())

    return types.float32(bits), codegen


def stored_value(a, i):
    """``a[i]`` as a float32 value: a float array's entry, or a uint16 array's bfloat16 decoded
    (in numba kernels; the decode is picked when the kernel is compiled for ``a``'s type)."""
    return from_bfloat16(a[i]) if a.dtype == np.uint16 else a[i]


@overload(stored_value, inline="always")
def _stored_value(a, i):
    if isinstance(a, types.Array) and a.dtype == types.uint16:
        return lambda a, i: _float32_from_bits(np.uint32(a[i]) << 16)
    return lambda a, i: a[i]
