"""CRC-32 (zlib's) of a concatenation from the CRCs of its parts, without reading either again.

A streamed NPZ (``apcg_core.io.clouds.CloudWriter``) knows the CRC of each array's bytes as they
are written, long before it knows the .npy header that goes in front of them in the zip member
(the header holds the final shape). CRC-32 is linear over GF(2): appending n zero bytes to a
message multiplies its CRC register by a fixed 32 x 32 bit matrix, so crc(A + B) is crc(A)
advanced over len(B) zero bytes, xor crc(B); the matrix for len(B) bytes is built by repeated
squaring (about 2 log2(len(B)) products of 32 x 32 bit matrices: microseconds).
"""

from __future__ import annotations

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
    """zlib.crc32(a + b) from crc_a = zlib.crc32(a), crc_b = zlib.crc32(b) and len(b)."""
    if len_b < 0:
        raise ValueError(f"len_b must be >= 0, got {len_b}")
    if len_b == 0:
        return crc_a
    # the operator of one zero bit: shift right, folding the polynomial in on a carry
    one_bit = [POLY] + [1 << (i - 1) for i in range(1, 32)]
    op = _square(_square(_square(one_bit)))  # one zero byte (8 bits)
    while True:
        if len_b & 1:
            crc_a = _times(op, crc_a)
        len_b >>= 1
        if not len_b:
            break
        op = _square(op)  # twice as many zero bytes
    return crc_a ^ crc_b


__all__ = ["crc32_combine"]
