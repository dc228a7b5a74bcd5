"""CRC-32 (zlib's) of a concatenation from the CRCs of its parts, without reading either again.

A streamed NPZ (``apcg_core.io.clouds.CloudWriter``) knows the CRC of each array's bytes as they
are written, long before it knows the .npy header that goes in front of them in the zip member
(the header holds the final shape). CRC-32 is linear over GF(2): appending n zero bytes to a
message multiplies its CRC register by a fixed 32 x 32 bit matrix, so crc(A + B) is crc(A)
advanced over len(B) zero bytes, xor crc(B); the matrix for len(B) bytes is the product of
those of the powers of two in len(B), each made by squaring once per process and kept (a
combine then costs one matrix-vector product per set bit of len(B): ~30 us in Python; squaring
anew on every call took 2.6 ms, 2.5 s of a 200,000-cloud job's final copy).
"""

from __future__ import annotations

import functools


def _fastest_crc32():
    """zlib's CRC-32 function, from ISA-L where it is installed (``isal``, the io extra: the
    same values, bit for bit, 9.8-10.0 GB/s against zlib's 2.3-2.4 GB/s on this project's
    2-core EPYC: ``bench/crc32.py``, stop 51), else from zlib. Both release the GIL on
    large buffers."""
    try:
        from isal.isal_zlib import crc32
    except ImportError:
        from zlib import crc32
    return crc32


# crc32(data, start=0): every CRC this package takes of bytes it writes or checks (the NPZ's
# members as blocks stream in, a generation job's parts) is taken by this one function
crc32 = _fastest_crc32()

POLY = 0xEDB88320  # CRC-32 (IEEE 802.3, zlib), bit-reflected


def _times(matrix: list[int], vector: int) -> int:
    """matrix (32 columns, each an int) times vector over GF(2)."""
    out, i = 0, 0
    while vector:
        if vector & 1:
            out ^= matrix[i]
        vector >>= 1
        i += 1
    return out


def _square(matrix: list[int]) -> list[int]:
    return [_times(matrix, column) for column in matrix]


def crc32_combine(crc_a: int, crc_b: int, len_b: int) -> int:
    """crc32(a + b) from crc_a = crc32(a), crc_b = crc32(b) and len(b)."""
    if len_b < 0:
        raise ValueError(f"len_b must be >= 0, got {len_b}")
    k = 0
    while len_b:
        if len_b & 1:
            crc_a = _times(_zero_bytes(k), crc_a)
        len_b >>= 1
        k += 1
    return crc_a ^ crc_b


@functools.cache
def _zero_bytes(k: int) -> tuple:
    """The operator of 2^k zero bytes, each squared once per process (a combine is then at
    most 64 matrix-vector products: tens of microseconds, not milliseconds)."""
    if k == 0:
        # the operator of one zero bit: shift right, folding the polynomial in on a carry
        one_bit = [POLY] + [1 << (i - 1) for i in range(1, 32)]
        return tuple(_square(_square(_square(one_bit))))  # one zero byte (8 bits)
    return tuple(_square(list(_zero_bytes(k - 1))))  # twice as many zero bytes


__all__ = ["crc32", "crc32_combine"]
