"""Exact similarities of SIFT descriptors in COLMAP's uint8 encoding, as COLMAP's matcher computes
them: the dot product of the bytes, an integer, whose angle is acos(min(dot / 512², 1)).

The per-image matching of SIFT + PnP's evidence (`verified_matching`) compares a query's keypoints
with the mapping images' own observations, whose descriptors the landmarks carry in that encoding
(the query's are encoded once, `QueryFeatures.codes`). Every such dot is an integer below
255² x 128 < 2^24, so a float32 product of the bytes is exact whatever the order of its sums:
numpy's BLAS, torch's and a GPU's (without TF32, torch's default) give the same numbers, and so
the same matches, on every machine and any thread count. On a CPU with int8 dot-product units
(VNNI or AMX) the products run as int8 matrix products (`torch._int_mm` on the bytes less 128, the
offsets added back), about 2.5x the float32 product's speed on mini's images (docs/results.md);
elsewhere as float32 products of the bytes. Both give the same integers."""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass

import numpy as np
import torch

DOT_SCALE = 512.0 ** 2  # COLMAP's kDistNorm: the dot of two unit descriptors, each encoded at 512
_SHIFT = 128  # a byte b as the signed byte b - 128
_DIMS = 128  # SIFT's descriptor length
MASKED = -1  # below every dot of bytes (all are >= 0): a masked entry never wins a maximum


@functools.lru_cache(maxsize=1)
def int8_products() -> bool:
    """Whether the products run as int8 matrix products: torch has them on the CPU and the CPU has
    int8 dot-product units (VNNI or AMX); else as float32 products (the same integers)."""
    if not hasattr(torch, "_int_mm"):
        return False
    units = [getattr(torch.cpu, name, None) for name in ("_is_vnni_supported", "_is_amx_tile_supported")]
    if not any(callable(u) and bool(u()) for u in units):
        return False
    try:  # a torch build without the CPU kernel raises here
        torch._int_mm(torch.zeros(1, _DIMS, dtype=torch.int8), torch.zeros(_DIMS, 1, dtype=torch.int8))
    except (RuntimeError, NotImplementedError):
        return False
    return True


@dataclass(frozen=True)
class ByteRows:
    """Descriptors in COLMAP's uint8 encoding, held as the products take them: as signed bytes
    with each row's offset (int8 products) or as float32 values (float32 products)."""

    codes: np.ndarray  # (n,128) uint8
    signed: torch.Tensor | None  # (n,128) int8: codes - 128 (int8 products only)
    offset: torch.Tensor | None  # (n,) int32: 128 x the row's sum of signed bytes (int8 products only)
    values: np.ndarray | None  # (n,128) float32: the codes (float32 products only)

    @classmethod
    def of(cls, codes: np.ndarray, int8: bool | None = None) -> ByteRows:
        """`codes` ((n,128) uint8) held for `int8` products (default: `int8_products()`)."""
        codes = np.ascontiguousarray(codes, dtype=np.uint8).reshape(-1, _DIMS)
        if int8 if int8 is not None else int8_products():
            signed = torch.from_numpy((codes.astype(np.int16) - _SHIFT).astype(np.int8))
            return cls(codes, signed, _SHIFT * signed.sum(dim=1, dtype=torch.int32), None)
        return cls(codes, None, None, codes.astype(np.float32))

    def __len__(self) -> int:
        return len(self.codes)

    def take(self, rows: np.ndarray) -> ByteRows:
        """The rows `rows` (indices), held as these are."""
        rows = np.asarray(rows, dtype=np.int64)
        if self.signed is not None:
            index = torch.from_numpy(rows)
            return ByteRows(self.codes[rows], self.signed.index_select(0, index), self.offset.index_select(0, index),
                            None)
        return ByteRows(self.codes[rows], None, None, self.values[rows])

    def floats(self) -> np.ndarray:
        """The codes as float32 values (for products on another device)."""
        return self.values if self.values is not None else self.codes.astype(np.float32)


def dots(a: ByteRows, b: ByteRows, out: np.ndarray | None = None) -> np.ndarray:
    """(len(a), len(b)) dot products of the bytes, exact: int32 from int8 products, float32 from
    float32 products (the same integers). `out`: a block of at least that many entries of the
    product's dtype (`dtype_of`) to hold them, reused from call to call (a fresh one costs its page
    faults)."""
    n, m = len(a), len(b)
    if (a.signed is None) != (b.signed is None):
        raise ValueError("dots: both sides must be held for the same products (ByteRows.of with one int8 setting)")
    if a.signed is not None:
        block = None if out is None or out.size < n * m or out.dtype != np.int32 else \
            torch.from_numpy(out[:n * m]).view(n, m)
        c = torch._int_mm(a.signed, b.signed.T, out=block) if block is not None else torch._int_mm(a.signed, b.signed.T)
        c += a.offset[:, None]
        c += (b.offset + _SHIFT * _SHIFT * _DIMS)[None, :]
        return c.numpy()
    block = None if out is None or out.size < n * m or out.dtype != np.float32 else out[:n * m].reshape(n, m)
    return np.matmul(a.values, b.values.T, out=block)


def dtype_of(rows: ByteRows) -> np.dtype:
    """The dtype of `dots` for rows held as `rows` are."""
    return np.dtype(np.int32) if rows.signed is not None else np.dtype(np.float32)


def angles(dot: np.ndarray) -> np.ndarray:
    """The angle (rad) of each dot of bytes, as COLMAP's matcher measures it: acos(min(dot / 512², 1));
    inf where the entry is MASKED (no such neighbour)."""
    d = np.asarray(dot, dtype=np.float64)
    return np.where(d >= 0, np.arccos(np.clip(d / DOT_SCALE, -1.0, 1.0)), np.inf)


class ProductBlocks:
    """Each thread's block for one image's products (`size` entries of `dtype`, made once per thread
    and reused from image to image: a fresh block per image costs its page faults)."""

    def __init__(self, size: int, dtype: np.dtype) -> None:
        self.size, self.dtype, self._local = int(size), np.dtype(dtype), threading.local()

    def block(self) -> np.ndarray:
        block = getattr(self._local, "block", None)
        if block is None:
            block = self._local.block = np.empty(self.size, self.dtype)
        return block
