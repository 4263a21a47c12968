"""Matching a list of image pairs on several threads with the bits of one.

COLMAP's own matcher threads take pairs as they come, and a pair's matches come out in the
order its two images were handed over, which then seeds geometric verification: threaded
matching gave a few points more or fewer between identical runs. Here the pairs are fixed in
advance, each oriented as COLMAP's exhaustive matcher orients it, and cut into contiguous
chunks; each chunk is matched by pycolmap on one matcher thread into its own copy of the
database, and the copies' rows are merged into the first. A pair's matches and two-view geometry
do not depend on which chunk it is in, so any thread count gives the database (and the model)
that one thread gives. The first chunk runs in this process and every other in a process of its
own: two pycolmap matchers running at once in one process now and then dropped part of a pair's
matches (mini's 1,770 pairs: one pair with 175 matches instead of 277, about one run in ten),
which matchers in separate processes cannot do to each other.
"""

from __future__ import annotations

import shutil
import sqlite3
import subprocess
import sys
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


def colmap_matching(seed: int) -> dict:
    """Matcher and seeded geometric-verification options for pycolmap's match_* calls (CPU), one
    matcher thread: COLMAP's threads take pairs as they come, and threaded matching gave a few points
    more or fewer between identical runs (3,214-3,235 of 3,235 on a 24-image scene, rarely)."""
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = 1
    mo.use_gpu = False
    vo = pycolmap.TwoViewGeometryOptions()
    vo.ransac.random_seed = seed  # COLMAP's default (-1) reseeds every run
    return dict(matching_options=mo, verification_options=vo, device=pycolmap.Device.cpu)


def _match_file(db_path: Path, pairs_file: Path, seed: int) -> None:
    po = pycolmap.ImportedPairingOptions()
    po.match_list_path = pairs_file
    pycolmap.match_image_pairs(db_path, pairing_options=po, **colmap_matching(seed))


def _write_pairs(pairs: list[tuple[str, str]], pairs_file: Path) -> Path:
    pairs_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    return pairs_file


def _matched_pairs(db_path: Path) -> int:
    con = sqlite3.connect(db_path)
    try:
        return int(con.execute("SELECT COUNT(*) FROM matches").fetchone()[0])
    finally:
        con.close()


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


def match_pairs(db_path: Path, pairs: list[tuple[str, str]], work_dir: Path, seed: int, threads: int) -> None:
    """Match and verify `pairs` into `db_path` (keypoints and descriptors already there) in up to
    `threads` chunks side by side, one pycolmap matcher thread each (`colmap_matching(seed)`): the
    first in this process, every other in a process of its own (this module's `_main`); the same
    rows whatever `threads` is."""
    parts = chunks(pairs, threads)
    dbs = [db_path] + [work_dir / f"matching_part{k}.db" for k in range(1, len(parts))]
    for db in dbs[1:]:
        shutil.copyfile(db_path, db)
    files = [_write_pairs(part, work_dir / f"matching_part{k}.txt") for k, part in enumerate(parts)]
    # The workers import this very file's package first, whatever the working directory holds.
    entry = f"import sys; sys.path.insert(0, {str(Path(__file__).resolve().parents[2])!r}); " \
            "from usvc.sfm.pair_matching import _main; _main(sys.argv[1:])"
    logs = [work_dir / f"matching_part{k}.log" for k in range(1, len(parts))]
    workers = []
    for db, f, log in zip(dbs[1:], files[1:], logs):
        with open(log, "w") as stderr:  # COLMAP's log lines, read back only if the process fails
            workers.append(subprocess.Popen([sys.executable, "-c", entry, str(db), str(f), str(seed),
                                             str(int(pycolmap.logging.minloglevel))], stderr=stderr))
    try:
        _match_file(dbs[0], files[0], seed)
    finally:
        for worker in workers:
            worker.wait()
    for worker, log in zip(workers, logs):
        if worker.returncode != 0:
            last = log.read_text(errors="replace").strip().splitlines()[-1:] or ["no message"]
            raise RuntimeError(f"a matching process exited with status {worker.returncode}: {last[0]}")
    for db, part in zip(dbs[1:], parts[1:]):
        if _matched_pairs(db) != len(part):
            raise RuntimeError(f"a matching process left {_matched_pairs(db)} of its {len(part)} pairs in {db}")
    if len(parts) > 1:
        _merge(db_path, dbs[1:])
    for path in dbs[1:] + files + logs:
        path.unlink(missing_ok=True)


def _main(argv: list[str]) -> None:
    """A matching process: DATABASE PAIRS_FILE SEED MINLOGLEVEL (match_pairs starts it)."""
    db, pairs_file, seed, minloglevel = argv
    pycolmap.logging.minloglevel = int(minloglevel)
    _match_file(Path(db), Path(pairs_file), int(seed))
