"""queries.h5, the relocalize stage's per-query records: its one writer and its readers.

Written by `usvc.relocalize.run.write_results` beside poses.txt; read by the metrics
stage. Every dataset carries
units/description/frame attributes (QUERIES_SCHEMA; docs/artifacts.md). Timings are not part of
the file (two runs that give the same poses give the same bytes): files written before that
change may hold `seconds` (and per-step `*_seconds`), which `read_query_stats` still reads.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from usvc.core.errors import UsvcError
from usvc.core.h5_file import Field, read_h5, write_h5

QUERIES_FORMAT, QUERIES_VERSION = "usvc-queries", 1

QUERIES_SCHEMA: dict[str, Field] = {
    "name": Field("1", "query image name (a test frame of prepared/scene.h5)"),
    "success": Field("1", "true: the pose was accepted (it is in poses.txt)"),
    "inliers": Field("1", "dense RANSAC inlier count (cells) of the query's pose"),
    "cells": Field("1", "8x8 cells (feature-map positions) of the query image; confidence = inliers / cells"),
    "refine_iterations": Field("1", "refinement iterations run on the dense pose (0: none)"),
    "refine_kept": Field("1", "true: the refined pose replaced the dense RANSAC pose"),
    "initial_R": Field("1", "world-to-camera rotation of the dense RANSAC pose before refinement: "
                            "x_cam = R x_world + t, OpenCV camera axes; NaN where success is false",
                       "world->camera"),
    "initial_t": Field("scene units", "world-to-camera translation of the dense RANSAC pose before refinement: "
                                      "x_cam = R x_world + t; NaN where success is false", "camera"),
}
REFINEMENT_DATASETS: tuple[str, ...] = ("initial_R", "initial_t", "refine_iterations", "refine_kept")


def write_queries(path: Path, names: Sequence[str], success: Sequence[bool], inliers: Sequence[int],
                  cells: Sequence[int], refine_iterations: Sequence[int], refine_kept: Sequence[bool],
                  initial_R: Sequence[np.ndarray], initial_t: Sequence[np.ndarray]) -> None:
    """One row per query, in the order given; initial_R/initial_t become NaN where success is false."""
    with write_h5(path, QUERIES_SCHEMA, QUERIES_FORMAT, QUERIES_VERSION) as h5:
        h5.create_dataset("name", data=np.array(list(names), dtype=object), dtype=h5py.string_dtype())
        h5["success"] = np.array(success)
        h5["inliers"] = np.array(inliers, dtype=np.int64)
        h5["cells"] = np.array(cells, dtype=np.int64)
        # Refinement records: the dense RANSAC pose before refinement (NaN where it failed), so the
        # metrics stage can score "refinement off" from the same run.
        h5["refine_iterations"] = np.array(refine_iterations, dtype=np.int64)
        h5["refine_kept"] = np.array(refine_kept, dtype=bool)
        h5["initial_R"] = np.array([R if ok else np.full((3, 3), np.nan) for R, ok in zip(initial_R, success)],
                                   dtype=np.float64).reshape(-1, 3, 3)
        h5["initial_t"] = np.array([t if ok else np.full(3, np.nan) for t, ok in zip(initial_t, success)],
                                   dtype=np.float64).reshape(-1, 3)


@dataclass(frozen=True)
class QueryStats:
    """What the relocalize stage reports for one query besides its pose."""

    inliers: int
    seconds: float | None  # total time for this query (None: not recorded in queries.h5)
    success: bool


def read_query_stats(path: Path | str) -> dict[str, QueryStats]:
    """Read `queries.h5` (datasets name, inliers, success; seconds when recorded) into {name: QueryStats}."""
    path = Path(path)
    if not path.is_file():
        raise UsvcError(f"query statistics not found: {path} (run the relocalize stage first)")
    with read_h5(path, "query statistics") as h5:
        missing = [k for k in ("name", "inliers", "success") if k not in h5]
        if missing:
            raise UsvcError(f"{path}: missing dataset(s) {missing}")
        names = [n.decode() if isinstance(n, bytes) else str(n) for n in h5["name"][()]]
        inliers, success = h5["inliers"][()], h5["success"][()]
        seconds = h5["seconds"][()] if "seconds" in h5 else [None] * len(names)
    if not (len(names) == len(inliers) == len(seconds) == len(success)):
        raise UsvcError(f"{path}: datasets name/inliers/seconds/success differ in length "
                        f"({len(names)}, {len(inliers)}, {len(seconds)}, {len(success)})")
    if len(set(names)) != len(names):
        raise UsvcError(f"{path}: duplicate query names")
    return {n: QueryStats(int(i), None if s is None else float(s), bool(ok))
            for n, i, s, ok in zip(names, inliers, seconds, success)}


@dataclass(frozen=True)
class RefinementRecords:
    """Per-query refinement records of `queries.h5`: the dense pose before refinement and what it did.

    `initial_R`, `initial_t` are world-to-camera (x_cam = R x_world + t).
    """

    names: list[str]
    success: np.ndarray  # (Q,) bool
    initial_R: np.ndarray  # (Q,3,3), NaN for failed queries
    initial_t: np.ndarray  # (Q,3)
    iterations: np.ndarray  # (Q,) int
    kept: np.ndarray  # (Q,) bool


def read_refinement_records(path: Path | str) -> RefinementRecords | None:
    """The refinement datasets of `queries.h5`, or None for a file written before refinement existed."""
    path = Path(path)
    if not path.is_file():
        raise UsvcError(f"query statistics not found: {path} (run the relocalize stage first)")
    with read_h5(path, "query statistics") as h5:
        present = [k for k in REFINEMENT_DATASETS if k in h5]
        if not present:
            return None
        missing = [k for k in ("name", "success", *REFINEMENT_DATASETS) if k not in h5]
        if missing:
            raise UsvcError(f"{path}: has refinement records but lacks dataset(s) {missing}")
        names = [n.decode() if isinstance(n, bytes) else str(n) for n in h5["name"][()]]
        rec = RefinementRecords(names, np.asarray(h5["success"][()], bool),
                                np.asarray(h5["initial_R"][()], np.float64),
                                np.asarray(h5["initial_t"][()], np.float64),
                                np.asarray(h5["refine_iterations"][()], np.int64),
                                np.asarray(h5["refine_kept"][()], bool))
    q = len(names)
    shapes = {"success": (rec.success.shape, (q,)), "initial_R": (rec.initial_R.shape, (q, 3, 3)),
              "initial_t": (rec.initial_t.shape, (q, 3)), "refine_iterations": (rec.iterations.shape, (q,)),
              "refine_kept": (rec.kept.shape, (q,))}
    for key, (got, want) in shapes.items():
        if got != want:
            raise UsvcError(f"{path}: dataset {key} has shape {got}, expected {want} for {q} queries")
    return rec


def refinement_summary(kept: Sequence[bool] | np.ndarray, iterations: Sequence[int] | np.ndarray) -> dict[str, float]:
    """refine_kept_fraction and refine_mean_iterations over the given (successful) queries; 0 if none."""
    return {"refine_kept_fraction": float(np.mean(kept)) if len(kept) else 0.0,
            "refine_mean_iterations": float(np.mean(iterations)) if len(iterations) else 0.0}
