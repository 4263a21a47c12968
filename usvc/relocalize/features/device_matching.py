"""The descriptor products of refinement by features on a torch device (a GPU), where the
relocalizer's network runs there: the landmarks x keypoints similarities and their row and column
reductions, computed on the device, and only the few numbers per row that matching needs brought
back. On the CPU the relocalizer keeps numpy's products (`matching`), whose answers the
tests and benchmarks pin; these functions compute the same reductions (a test holds them to
numpy's on the CPU), so a query on a GPU matches as one on the CPU does, up to the last bits of
the products (a near-tie in the ratio test may fall the other way)."""

from __future__ import annotations

import numpy as np
import torch

_CHUNK_ENTRIES = 1 << 26  # similarities (4 bytes each) per block on the device: 256 MB


def matching_device(device: str) -> str | None:
    """Where a relocalizer on `device` computes its descriptor products: on a GPU there, on the CPU
    with numpy (None), whose matches the CPU figures were measured with."""
    return device if torch.device(device).type != "cpu" else None


def _tensor(a: np.ndarray, device: torch.device) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(device)


def masked_row_best_two(rows: np.ndarray, cols: np.ndarray, pair_rows: np.ndarray, pair_cols: np.ndarray,
                        device: str | torch.device) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row of `rows` (`byte_products.scaled` rows: exact products): among the `cols` descriptors paired with it
    (`pair_rows`, `pair_cols`: the pairs in reach), the column of the largest similarity and the
    largest and second largest (-inf where fewer): `_row_best_two` of the masked product."""
    device = torch.device(device)
    with torch.inference_mode():
        sim = _tensor(rows, device) @ _tensor(cols, device).T
        far = torch.ones(sim.shape, dtype=torch.bool, device=device)
        far[torch.from_numpy(pair_rows).to(device), torch.from_numpy(pair_cols).to(device)] = False
        sim.masked_fill_(far, float("-inf"))
        return _top_two(sim)


def _top_two(sim: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    k = min(2, sim.shape[1])
    values, index = torch.topk(sim, k, dim=1)
    s1, first = values[:, 0], index[:, 0]
    s2 = values[:, 1] if k == 2 else torch.full_like(s1, float("-inf"))
    return first.cpu().numpy().astype(np.int64), s1.cpu().numpy(), s2.cpu().numpy()


def best_two_and_column_max(query: np.ndarray, landmarks: np.ndarray,
                            device: str | torch.device) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the keypoints' descriptors (`byte_products.scaled` rows) `query` against every landmark's `landmarks`: each
    keypoint's two largest similarities (largest first) and the landmark of the largest, and each
    landmark's largest similarity to a keypoint. Blocks of landmarks bound the device memory."""
    device = torch.device(device)
    k = len(query)
    with torch.inference_mode():
        q = _tensor(query, device)
        best = torch.full((k, 2), float("-inf"), device=device)
        best_i = torch.zeros(k, dtype=torch.int64, device=device)
        lm_max = torch.empty(len(landmarks), device=device)
        step = max(2, _CHUNK_ENTRIES // max(k, 1))
        for start in range(0, len(landmarks), step):
            sim = q @ _tensor(landmarks[start:start + step], device).T  # (K, block)
            lm_max[start:start + sim.shape[1]] = sim.max(dim=0).values
            values, index = torch.topk(sim, min(2, sim.shape[1]), dim=1)
            if values.shape[1] == 1:
                values = torch.cat([values, torch.full_like(values, float("-inf"))], dim=1)
            best_i = torch.where(values[:, 0] > best[:, 0], index[:, 0] + start, best_i)
            best = torch.sort(torch.cat([best, values], dim=1), dim=1, descending=True).values[:, :2]
        return best.cpu().numpy(), best_i.cpu().numpy(), lm_max.cpu().numpy()


def mutual_reductions(query: np.ndarray, image: np.ndarray,
                      device: str | torch.device) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What COLMAP's matcher rules need of the query x image similarities (`verified_matching.
    mutual_ratio_matches`: `query` and `image` are the uint8 codes as float32, whose products are
    exact integers where TF32 is off, torch's default), computed on `device`: per query row the
    column of its largest entry (the first on ties), the largest and the second largest (-inf for a
    single column); per image
    column the first row that reaches its largest entry. numpy's argmax rule throughout: torch's
    argmax returns the first maximal index too."""
    device = torch.device(device)
    with torch.inference_mode():
        sim = _tensor(query, device) @ _tensor(image, device).T  # (K, n)
        reach = torch.argmax((sim == sim.max(dim=0, keepdim=True).values).to(torch.uint8), dim=0)
        first, s1, s2 = _first_two(sim)
        return first, s1, s2, reach.cpu().numpy().astype(np.int64)


def two_way_reductions(query: np.ndarray, image: np.ndarray, device: str | torch.device
                       ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """What COLMAP's cross-checked matching needs of the query x image similarities
    (`verified_matching.cross_checked_matches`; the uint8 codes as float32: exact integer products),
    computed on `device`: per query row and per image column, the index of the largest entry (the
    first on ties), the largest and the second largest (-inf where there is one entry)."""
    device = torch.device(device)
    with torch.inference_mode():
        sim = _tensor(query, device) @ _tensor(image, device).T  # (K, n)
        return _first_two(sim.clone()), _first_two(sim.T.contiguous())


def _first_two(sim: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row of `sim` (masked in place): the index of the largest entry (the first on ties, as
    numpy's argmax), the largest and the second largest (-inf where there is one column)."""
    rows = torch.arange(sim.shape[0], device=sim.device)
    first = torch.argmax(sim, dim=1)
    s1 = sim[rows, first]
    if sim.shape[1] > 1:
        sim[rows, first] = float("-inf")
        s2 = sim.max(dim=1).values
    else:
        s2 = torch.full_like(s1, float("-inf"))
    return first.cpu().numpy().astype(np.int64), s1.cpu().numpy(), s2.cpu().numpy()
