"""Exact similarities of SIFT descriptors in COLMAP's uint8 encoding, as COLMAP's matcher computes
them: the dot product of the bytes, an integer, whose angle is acos(min(dot / 512², 1)).

The per-image matching of SIFT + PnP's evidence (`verified_matching`) compares a query's keypoints
with the mapping images' own observations, whose descriptors the landmarks carry in that encoding
(the query's are encoded once, `QueryFeatures.codes`). Every such dot is an integer below
255² x 128 < 2^24, so a float32 product of the bytes is exact whatever the order of its sums:
numpy's BLAS, torch's and a GPU's (without TF32, torch's default) give the same numbers, and so
the same matches, on every machine and any thread count. On a CPU with int8 dot-product units
(VNNI or AMX) the products run as int8 matrix products (`torch._int_mm` on the bytes less 128, the
offsets added back), about 2.5x the float32 product's speed on mini's images (docs/results.md),
for products of at least INT8_MIN_ENTRIES entries (below, torch's per-call cost outweighs it);
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
INT8_MIN_ENTRIES = 65536  # smaller products run as float32 products: torch's calls cost more than they save


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
    """Descriptors in COLMAP's uint8 encoding, held as the products take them: as float32 values
    and, for int8 products, as signed bytes with each row's offset (for rows taken from such a
    set, gathered from it only when a product runs on int8 units)."""

    values: np.ndarray  # (n,128) float32: the codes
    signed: torch.Tensor | None = None  # (n,128) int8: codes - 128 (int8 products only)
    offset: torch.Tensor | None = None  # (n,) int32: 128 x the row's sum of signed bytes (int8 products only)
    source: ByteRows | None = None  # the set these rows were taken from (with `rows`), when it holds signed bytes
    rows: np.ndarray | None = None

    @classmethod
    def of(cls, codes: np.ndarray, int8: bool | None = None) -> ByteRows:
        """`codes` ((n,128) uint8) held for `int8` products too (default: `int8_products()`)."""
        codes = np.ascontiguousarray(codes, dtype=np.uint8).reshape(-1, _DIMS)
        values = codes.astype(np.float32)
        if int8 if int8 is not None else int8_products():
            signed = torch.from_numpy((codes.astype(np.int16) - _SHIFT).astype(np.int8))
            return cls(values, signed, _SHIFT * signed.sum(dim=1, dtype=torch.int32))
        return cls(values)

    def __len__(self) -> int:
        return len(self.values)

    def take(self, rows: np.ndarray) -> ByteRows:
        """The rows `rows` (indices), held as these are."""
        rows = np.asarray(rows, dtype=np.int64)
        base, index = (self, rows) if self.source is None else (self.source, self.rows[rows])
        if base.signed is None:
            return ByteRows(self.values[rows])
        return ByteRows(self.values[rows], source=base, rows=index)

    def rows_between(self, start: int, stop: int) -> ByteRows:
        """Rows start to stop (views of these, without a copy, where these are not taken rows)."""
        if self.source is not None:
            return self.take(np.arange(start, stop))
        if self.signed is None:
            return ByteRows(self.values[start:stop])
        return ByteRows(self.values[start:stop], self.signed[start:stop], self.offset[start:stop])

    def int8(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(signed bytes, offsets) of these rows, or None where they are held for float32 products only."""
        if self.signed is not None:
            return self.signed, self.offset
        if self.source is None:
            return None
        index = torch.from_numpy(np.ascontiguousarray(self.rows))
        return self.source.signed.index_select(0, index), self.source.offset.index_select(0, index)


class ProductBlocks:
    """Each thread's blocks for one image's products (at least `size` entries of each dtype asked
    for, made once per thread and reused from image to image: a fresh block per image costs its
    page faults)."""

    def __init__(self, size: int) -> None:
        self.size, self._local = int(size), threading.local()

    def block(self, dtype: type, entries: int) -> np.ndarray:
        """The first `entries` entries of this thread's block of `dtype`."""
        blocks = self._local.__dict__.setdefault("blocks", {})
        key = np.dtype(dtype).str
        if key not in blocks or blocks[key].size < entries:
            blocks[key] = np.empty(max(self.size, entries), dtype)
        return blocks[key][:entries]


def dots(a: ByteRows, b: ByteRows, blocks: ProductBlocks | None = None) -> np.ndarray:
    """(len(a), len(b)) dot products of the bytes, exact: int32 from int8 products (where both
    sides hold signed bytes and the product has at least INT8_MIN_ENTRIES entries), else float32
    from float32 products (the same integers). `blocks`: the calling thread's reusable blocks to
    hold them (a fresh array per call costs its page faults)."""
    n, m = len(a), len(b)
    held = (a.signed is not None or a.source is not None) and (b.signed is not None or b.source is not None)
    if held and n * m >= INT8_MIN_ENTRIES:
        (sa, oa), (sb, ob) = a.int8(), b.int8()
        out = None if blocks is None else torch.from_numpy(blocks.block(np.int32, n * m)).view(n, m)
        c = torch._int_mm(sa, sb.T, out=out) if out is not None else torch._int_mm(sa, sb.T)
        c += oa[:, None]
        c += (ob + _SHIFT * _SHIFT * _DIMS)[None, :]
        return c.numpy()
    out = None if blocks is None else blocks.block(np.float32, n * m).reshape(n, m)
    return np.matmul(a.values, b.values.T, out=out)


def scaled(codes: np.ndarray) -> np.ndarray:
    """Descriptors in COLMAP's uint8 encoding as float32 rows of code / 512: near-unit vectors whose
    float32 products are the bytes' exact integer dots / 512² (each term and partial sum an integer
    times 2^-18, below 2^6: exact in float32 in any order, as DOT_SCALE = 2^18). So matching by these
    similarities is matching by COLMAP's integer dots, the same on every CPU, BLAS and GPU."""
    return np.asarray(codes, dtype=np.uint8).reshape(-1, _DIMS).astype(np.float32) * np.float32(1.0 / 512.0)


def angles(dot: np.ndarray) -> np.ndarray:
    """The angle (rad) of each dot of bytes, as COLMAP's matcher measures it: acos(min(dot / 512², 1));
    inf where the entry is MASKED or -inf (no such neighbour)."""
    d = np.asarray(dot, dtype=np.float64)
    return np.where(d >= 0, np.arccos(np.clip(d / DOT_SCALE, -1.0, 1.0)), np.inf)
