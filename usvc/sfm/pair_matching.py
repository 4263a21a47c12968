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

COLMAP reads a pair list as text, cutting each line at its first space and skipping a line that
starts with `#`, so a photo named `IMG (1).jpg` or `#12.jpg` cannot be named there. While pairs
are matched, every image of the database goes by an alias made of its id (`aliased_names`): the
list names aliases only, the matches (keyed by image ids) are the same, and the names are put back
afterwards. Every chunk's count of matched pairs is checked, the one in this process too.
"""

from __future__ import annotations

import shutil
import sqlite3
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pycolmap

from usvc.core.errors import SfmError

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


_ALIAS = "usvc-image-{}"  # no space, no leading '#': a name COLMAP's pair list can hold


@contextmanager
def aliased_names(db_path: Path) -> Iterator[dict[str, str]]:
    """Every image of the database renamed to an alias of its id while the block runs (yields
    {name: alias}); the names are put back when it ends, however it ends."""
    con = sqlite3.connect(db_path)
    try:
        rows = con.execute("SELECT image_id, name FROM images").fetchall()
        aliases = {name: _ALIAS.format(image_id) for image_id, name in rows}
        clash = sorted(set(aliases) & set(aliases.values()))
        if clash:  # a photo named like an alias: renaming one onto the other would break the unique names
            raise SfmError(f"photo name {clash[0]!r} is reserved for matching; rename that photo")
        with con:
            con.execute("UPDATE images SET name = ? || image_id", (_ALIAS.format(""),))
    finally:
        con.close()
    try:
        yield aliases
    finally:
        con = sqlite3.connect(db_path)
        try:
            with con:
                con.executemany("UPDATE images SET name = ? WHERE image_id = ?", [(n, i) for i, n in rows])
        finally:
            con.close()


def _write_pairs(pairs: list[tuple[str, str]], pairs_file: Path, aliases: dict[str, str]) -> Path:
    pairs_file.write_text("".join(f"{aliases[a]} {aliases[b]}\n" for a, b in pairs))
    return pairs_file


def match_listed_pairs(db_path: Path, pairs: list[tuple[str, str]], pairs_file: Path, seed: int) -> None:
    """Match and verify `pairs` (image names, any characters) into `db_path` in this process, on one
    matcher thread (`colmap_matching(seed)`); `pairs_file` is a scratch path for COLMAP's list. Raises
    when COLMAP left any pair out."""
    before = _matched_pairs(db_path)
    with aliased_names(db_path) as aliases:
        _match_file(db_path, _write_pairs(pairs, pairs_file, aliases), seed)
    _check_count(db_path, _matched_pairs(db_path) - before, len(pairs))
    pairs_file.unlink(missing_ok=True)


def _check_count(db_path: Path, matched: int, expected: int) -> None:
    if matched != expected:
        raise RuntimeError(f"COLMAP matched {matched} of {expected} image pairs into {db_path}")


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
    with aliased_names(db_path) as aliases:
        _match_chunks(db_path, pairs, aliases, work_dir, seed, threads)


def _match_chunks(db_path: Path, pairs: list[tuple[str, str]], aliases: dict[str, str], work_dir: Path, seed: int,
                  threads: int) -> None:
    """match_pairs' work while the database's images go by `aliases`."""
    parts = chunks(pairs, threads)
    dbs = [db_path] + [work_dir / f"matching_part{k}.db" for k in range(1, len(parts))]
    for db in dbs[1:]:
        shutil.copyfile(db_path, db)
    files = [_write_pairs(part, work_dir / f"matching_part{k}.txt", aliases) for k, part in enumerate(parts)]
    before = _matched_pairs(db_path)
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
        if parts[0]:
            _match_file(dbs[0], files[0], seed)
    finally:
        for worker in workers:
            worker.wait()
    for worker, log in zip(workers, logs):
        if worker.returncode != 0:
            last = log.read_text(errors="replace").strip().splitlines()[-1:] or ["no message"]
            raise RuntimeError(f"a matching process exited with status {worker.returncode}: {last[0]}")
    _check_count(db_path, _matched_pairs(db_path) - before, len(parts[0]))
    for db, part in zip(dbs[1:], parts[1:]):
        _check_count(db, _matched_pairs(db) - before, len(part))
    if len(parts) > 1:
        _merge(db_path, dbs[1:])
    for path in dbs[1:] + files + logs:
        path.unlink(missing_ok=True)


def _main(argv: list[str]) -> None:
    """A matching process: DATABASE PAIRS_FILE SEED MINLOGLEVEL (match_pairs starts it)."""
    db, pairs_file, seed, minloglevel = argv
    pycolmap.logging.minloglevel = int(minloglevel)
    _match_file(Path(db), Path(pairs_file), int(seed))
