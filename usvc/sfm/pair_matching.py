"""Matching a list of image pairs on several threads with the bits of one.

COLMAP's own matcher threads take pairs as they come, and a pair's matches come out in the
order its two images were handed over, which then seeds geometric verification: threaded
matching gave a few points more or fewer between identical runs. Here the pairs are fixed in
advance, each oriented as COLMAP's exhaustive matcher orients it, and cut into contiguous
chunks; each chunk is matched by pycolmap on one thread (it releases Python's lock) into its
own copy of the database, and the copies' rows are merged into the first. A pair's matches and
two-view geometry do not depend on which chunk it is in, so any thread count gives the
database (and the model) that one thread gives.
"""

from __future__ import annotations

import shutil
import sqlite3
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pycolmap

# The tables a matching run fills; every other table is the extraction's, the same in each copy.
_MATCH_TABLES = ("matches", "two_view_geometries")


def image_names(db_path: Path) -> list[str]:
    """The database's image names in image-id order (the order COLMAP's exhaustive matcher walks)."""
    db = pycolmap.Database.open(db_path)
    try:
        return [im.name for im in sorted(db.read_all_images(), key=lambda im: im.image_id)]
    finally:
        db.close()


def exhaustive_pairs(names: list[str], block_size: int | None = None) -> list[tuple[str, str]]:
    """Every pair of `names` (in image-id order), in the order and orientation of COLMAP's
    exhaustive matcher: blocks of `block_size` images (COLMAP's default when None); positions i < j
    in blocks of their own are matched as (j, i) when j's place in its block is not after i's."""
    if block_size is None:
        block_size = pycolmap.ExhaustivePairingOptions().block_size
    n = len(names)
    pairs: list[tuple[str, str]] = []
    for start1 in range(0, n, block_size):
        for start2 in range(0, n, block_size):
            for i in range(start1, min(n, start1 + block_size)):
                for j in range(start2, min(n, start2 + block_size)):
                    bi, bj = i % block_size, j % block_size
                    if (i > j and bi <= bj) or (i < j and bi < bj):
                        pairs.append((names[i], names[j]))
    return pairs


def chunks(pairs: list[tuple[str, str]], count: int) -> list[list[tuple[str, str]]]:
    """`pairs` cut into at most `count` contiguous runs of nearly equal length (none empty)."""
    count = max(1, min(count, len(pairs)))
    return [pairs[k * len(pairs) // count:(k + 1) * len(pairs) // count] for k in range(count)]


def _match_chunk(db_path: Path, pairs: list[tuple[str, str]], pairs_file: Path, matching: dict) -> None:
    pairs_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    po = pycolmap.ImportedPairingOptions()
    po.match_list_path = pairs_file
    pycolmap.match_image_pairs(db_path, pairing_options=po, **matching)


def _merge(into: Path, others: list[Path]) -> None:
    con = sqlite3.connect(into)
    try:
        for other in others:
            con.execute("ATTACH DATABASE ? AS part", (str(other),))
            for table in _MATCH_TABLES:
                con.execute(f"INSERT INTO main.{table} SELECT * FROM part.{table}")
            con.commit()
            con.execute("DETACH DATABASE part")
    finally:
        con.close()


def match_pairs(db_path: Path, pairs: list[tuple[str, str]], work_dir: Path, matching: dict, threads: int) -> None:
    """Match and verify `pairs` into `db_path` (keypoints and descriptors already there) on up to
    `threads` threads, one pycolmap matcher thread each (`matching`: matching_kwargs's options, whose
    num_threads must be 1); the same rows whatever `threads` is."""
    if matching["matching_options"].num_threads != 1:
        raise ValueError("match_pairs runs one matcher thread per chunk: matching_options.num_threads must be 1")
    parts = chunks(pairs, threads)
    dbs = [db_path] + [work_dir / f"matching_part{k}.db" for k in range(1, len(parts))]
    for db in dbs[1:]:
        shutil.copyfile(db_path, db)
    files = [work_dir / f"matching_part{k}.txt" for k in range(len(parts))]
    if len(parts) == 1:
        _match_chunk(db_path, parts[0], files[0], matching)
    else:
        with ThreadPoolExecutor(len(parts)) as pool:
            for done in [pool.submit(_match_chunk, db, part, f, matching) for db, part, f in zip(dbs, parts, files)]:
                done.result()
        _merge(db_path, dbs[1:])
    for path in dbs[1:] + files:
        path.unlink(missing_ok=True)
