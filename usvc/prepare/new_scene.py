"""Add a scene to a usvc checkout in one step: its photos under ``data/raw/<name>``, its
``conf/scene/<name>.yaml``, its name in ``params.yaml``, then (optionally) ``dvc repro`` of it.

This is what ``usvc map PHOTOS --name NAME`` runs, in two phases:

1. **Check everything, write nothing**: the name (pattern, reserved words, collisions with conf/),
   the options (working width, metric scale), the folder (symbolic link loops, broken links), the
   capture itself (imported once with :func:`usvc.prepare.importers.import_scene`: format, enough
   photos to map and query, plausible EXIF focal lengths) and every photo decoded in full (a
   truncated JPEG fails here, not in ``prepare``).
2. **Register atomically** under an exclusive lock on the checkout (a second ``usvc map`` waits,
   then finds the name taken): photos, config and params entry are built as temporaries and
   renamed into place last, params.yaml last of all. Any failure, Ctrl-C, SIGTERM or SIGHUP
   undoes all of it, so a scene is never half-registered and a retry is never "already exists".
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import re
import shutil
import stat
import subprocess
import threading
from dataclasses import dataclass
from pathlib import Path

import yaml

from usvc.core.errors import UsvcError
from usvc.core.scene_names import scene_name_problem
from usvc.prepare.importers import FORMATS, import_scene
from usvc.prepare.options import MAX_WORKING_WIDTH, MIN_WORKING_WIDTH
from usvc.prepare.registration_guards import SignalGuard, checkout_lock

log = logging.getLogger(__name__)

LOCK_FILE = ".usvc-map.lock"  # in the checkout root, held while a scene is registered
SHOWN_PROBLEMS = 3
UNDISTORT_FOV = "crop"  # the scene config's undistort_fov (no black borders)


@dataclass(frozen=True)
class NewSceneOptions:
    name: str
    format: str = "images"
    split_n: int = 8  # every split_n-th photo is a query (never trained on)
    working_width: int = 640
    metric_scale: float | None = None  # metres per scene unit, when the poses are metric
    exif_focal: bool = True  # format images: EXIF focal lengths are SfM's prior (False: `--no-exif`)


def find_checkout(start: Path) -> Path:
    """The usvc checkout containing ``start`` (where dvc.yaml, params.yaml and conf/scene are)."""
    for folder in (start, *start.parents):
        if (folder / "dvc.yaml").is_file() and (folder / "params.yaml").is_file() and (folder / "conf" / "scene").is_dir():
            return folder
    raise UsvcError(f"{start} is not inside a usvc checkout (no dvc.yaml, params.yaml and conf/scene/ above it); "
                    "run `usvc map` from the repository")


def _scene_yaml(source: Path, opts: NewSceneOptions) -> str:
    scale = "null" if opts.metric_scale is None else repr(float(opts.metric_scale))
    where = str(source).encode("unicode_escape").decode("ascii")  # a newline in a folder name ends no comment
    exif = "exif_focal: true\n" if opts.exif_focal else \
        "exif_focal: false      # `usvc map --no-exif`: SfM estimates the focal length\n"
    return (f"# Added by `usvc map` from {where}\n"
            "defaults:\n  - base_scene\n  - _self_\n"
            f"name: {opts.name}\nformat: {opts.format}\npath: data/raw/{opts.name}\n"
            f"split: every_nth\nsplit_n: {opts.split_n}\nmetric_scale: {scale}\n"
            f"working_width: {opts.working_width}\nundistort_fov: {UNDISTORT_FOV}\ngenerated: false\n{exif}")


def _params_with(text: str, params: Path, name: str) -> str:
    """params.yaml's text with ``name`` appended to its ``scenes:`` list, comments kept."""
    lines = text.splitlines(keepends=True)
    try:
        start = next(i for i, line in enumerate(lines) if line.rstrip() == "scenes:")
    except StopIteration:
        raise UsvcError(f"{params}: no top-level 'scenes:' list to add the scene to") from None
    end = start + 1
    while end < len(lines) and (lines[end].startswith((" ", "\t")) or not lines[end].strip()):
        end += 1
    while end > start + 1 and not lines[end - 1].strip():
        end -= 1
    indent = next((re.match(r"\s*", line).group(0) for line in lines[start + 1:end] if line.strip()), "  ")
    if end == len(lines) and lines and not lines[-1].endswith("\n"):
        lines[-1] += "\n"
    lines.insert(end, f"{indent}- {name}\n")
    out = "".join(lines)
    if name not in (yaml.safe_load(out) or {}).get("scenes", []):
        raise UsvcError(f"{params}: could not add {name!r} to 'scenes' (is it a block list?)")
    return out


def _add_to_params(params: Path, name: str) -> None:
    """Append ``name`` to the ``scenes:`` list of params.yaml, keeping its comments (atomically)."""
    text = _params_with(params.read_text(), params, name)
    tmp = params.with_name(params.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, params)


def _params_scenes(params: Path) -> list:
    try:
        loaded = yaml.safe_load(params.read_text()) or {}
    except yaml.YAMLError as e:
        raise UsvcError(f"{params}: not valid YAML ({str(e).splitlines()[0]})") from None
    scenes = loaded.get("scenes", []) if isinstance(loaded, dict) else None
    if not isinstance(scenes, list):
        raise UsvcError(f"{params}: 'scenes' is not a list")
    return scenes


# ---------------------------------------------------------------- phase 1: checks, nothing written

def check_name(name: str, checkout: Path) -> None:
    """Refuse a name that breaks the pattern, is reserved, or is taken in ``checkout``."""
    problem = scene_name_problem(name)  # the rule every stage's scene.name obeys too
    if problem:
        raise UsvcError(f"scene name {name!r}{' ' if problem.startswith('is ') else ': '}{problem}; pick another --name")
    conf = checkout / "conf"
    for taken in (conf / f"{name}.yaml", conf / name):
        if taken.exists():
            what = "a config group" if taken.is_dir() else "a config file"
            raise UsvcError(f"scene name {name!r} is taken by {taken} ({what} of conf/); pick another --name")
    _check_free(name, checkout)


def _check_free(name: str, checkout: Path) -> None:
    conf = checkout / "conf" / "scene" / f"{name}.yaml"
    raw = checkout / "data" / "raw" / name
    params = checkout / "params.yaml"
    for taken, what in ((conf.exists() or conf.is_symlink(), str(conf)), (raw.exists() or raw.is_symlink(), str(raw)),
                        (name in _params_scenes(params), f"{params} scenes")):
        if taken:
            raise UsvcError(f"scene {name!r} already exists ({what}); pick another --name")


def check_options(opts: NewSceneOptions) -> None:
    """Refuse options no scene can be built with (one line naming the flag and the limit)."""
    if opts.format not in FORMATS:
        raise UsvcError(f"format {opts.format!r} is not one of {list(FORMATS)}")
    if not isinstance(opts.split_n, int) or opts.split_n < 2:
        raise UsvcError(f"--split-n {opts.split_n}: need >= 2 (every split_n-th photo is a query)")
    ww = opts.working_width
    if not isinstance(ww, int) or isinstance(ww, bool):
        raise UsvcError(f"--working-width {ww!r}: a whole number of pixels")
    if ww != 0 and ww < MIN_WORKING_WIDTH:
        raise UsvcError(f"--working-width {ww}: width too small: at least {MIN_WORKING_WIDTH} px "
                        "(0 keeps the photos' own width)")
    if ww > MAX_WORKING_WIDTH:
        raise UsvcError(f"--working-width {ww}: wider than any camera's photos: at most {MAX_WORKING_WIDTH} px "
                        "(0 keeps the photos' own width)")
    scale = opts.metric_scale
    if scale is not None:
        try:
            ok = math.isfinite(float(scale)) and float(scale) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise UsvcError(f"--metric-scale {scale!r}: must be a finite number > 0 (metres per scene unit)")
    if not opts.exif_focal and opts.format != "images":
        raise UsvcError(f"--no-exif applies to --format images only (format {opts.format!r} carries its own "
                        "intrinsics)")


def _scan_tree(source: Path) -> tuple[list[Path], list[Path]]:
    """(folders, files) under ``source``, relative to it, symbolic links followed; one line naming
    the link for a loop or a broken link (copytree would recurse forever or print a list)."""
    dirs: list[Path] = []
    files: list[Path] = []

    def target(path: Path) -> str:
        with contextlib.suppress(OSError):
            return f" -> {os.readlink(path)}"
        return ""

    def walk(folder: Path, rel: Path, ancestors: dict[tuple[int, int], Path]) -> None:
        try:
            entries = sorted(os.scandir(folder), key=lambda e: e.name)
        except OSError as e:
            raise UsvcError(f"cannot read folder {folder} ({e.strerror})") from None
        for entry in entries:
            path = Path(entry.path)
            try:
                st = os.stat(path)
            except OSError as e:
                if e.errno == errno.ELOOP:
                    raise UsvcError(f"symbolic link loop in the photo folder: {path}{target(path)}; "
                                    "remove the link") from None
                if entry.is_symlink() and e.errno == errno.ENOENT:
                    raise UsvcError(f"broken symbolic link in the photo folder: {path}{target(path)}; "
                                    "remove it or restore its target") from None
                raise UsvcError(f"cannot read {path} ({e.strerror})") from None
            if stat.S_ISDIR(st.st_mode):
                key = (st.st_dev, st.st_ino)
                if key in ancestors:
                    raise UsvcError(f"symbolic link loop in the photo folder: {path}{target(path)} leads back to "
                                    f"{ancestors[key]}, a folder it is in; remove the link")
                dirs.append(rel / entry.name)
                walk(path, rel / entry.name, {**ancestors, key: path})
            elif stat.S_ISREG(st.st_mode):
                files.append(rel / entry.name)
            else:
                log.warning("skipping %s: not a regular file or folder", path)

    root = os.stat(source)
    walk(source, Path(), {(root.st_dev, root.st_ino): source})
    return dirs, files


def _check_photos(scene, source: Path, opts: NewSceneOptions) -> None:
    """Enough photos to map and to query, cameras prepare will accept (focal lengths, distortion),
    each photo readable, decodable in full and of its camera's size: what prepare refuses must be
    refused before anything is registered."""
    from usvc.core.undistort import check_image_size
    from usvc.prepare.working_images import check_cameras, decoded
    from usvc.sfm.reconstruction import MIN_MAPPING_IMAGES

    n = len(scene.frames)
    n_query = sum(f.split == "test" for f in scene.frames)
    need = MIN_MAPPING_IMAGES + 1
    if n < need:
        raise UsvcError(f"need at least {need} photos (got {n}) in {source}: {MIN_MAPPING_IMAGES} to map (SfM keeps "
                        "only points seen in 3 or more) and 1 query")
    if n - n_query < MIN_MAPPING_IMAGES:
        raise UsvcError(f"{n} photos with --split-n {opts.split_n} leave {n - n_query} to map: need at least "
                        f"{MIN_MAPPING_IMAGES}; use a larger --split-n or more photos")
    scene.check_images_exist()
    scene.split("train")
    scene.split("test")
    check_cameras(scene.frames, UNDISTORT_FOV)
    widest = 0
    for i, frame in enumerate(scene.frames):
        image, camera = decoded(frame)  # SceneError naming the photo
        check_image_size(image, camera, str(frame.image_path))
        widest = max(widest, frame.camera.width)
        if i and i % 50 == 0:
            log.info("checked %d of %d photos", i, n)
    if opts.working_width > widest:
        log.warning("--working-width %d is wider than the photos (at most %d px): they are upscaled",
                    opts.working_width, widest)


def _check_writable(checkout: Path) -> None:
    for folder in (checkout, checkout / "conf" / "scene", checkout / "data" / "raw"):
        while not folder.exists():
            folder = folder.parent
        if not os.access(folder, os.W_OK | os.X_OK):
            raise UsvcError(f"{folder} is not writable: cannot add a scene to this checkout")


# ---------------------------------------------------------------- phase 2: atomic registration

def _copy_tree(src: Path, dst: Path, tree: tuple[list[Path], list[Path]] | None = None) -> None:
    """Hard links where the file system allows them (no second copy of the photos), else copies."""
    dirs, files = _scan_tree(src) if tree is None else tree
    dst.mkdir()
    for d in dirs:
        (dst / d).mkdir()
    for f in files:
        try:
            os.link(os.path.realpath(src / f), dst / f)  # a link's target (os.link may link the link itself)
        except OSError:
            try:
                shutil.copy2(src / f, dst / f)
            except OSError as e:
                raise UsvcError(f"cannot copy {src / f} to {dst / f} ({e.strerror})") from None


def _register(source: Path, checkout: Path, opts: NewSceneOptions, tree: tuple[list[Path], list[Path]]) -> None:
    """Photos, config and params entry, each built as a temporary and renamed into place last; on any
    failure or signal everything written so far is removed and params.yaml restored."""
    name = opts.name
    conf = checkout / "conf" / "scene" / f"{name}.yaml"
    raw = checkout / "data" / "raw" / name
    params = checkout / "params.yaml"
    tag = f"{os.getpid()}-{threading.get_ident()}"
    raw_tmp = raw.with_name(f".{name}.partial-{tag}")
    conf_tmp = conf.with_name(f".{name}.yaml.partial-{tag}")
    params_tmp = params.with_name(params.name + ".tmp")
    created = [d for d in (checkout / "data", checkout / "data" / "raw") if not d.exists()]
    old_params = params.read_text()
    placed: list[Path] = []
    with SignalGuard() as guard:
        try:
            raw.parent.mkdir(parents=True, exist_ok=True)
            _copy_tree(source, raw_tmp, tree)
            conf_tmp.write_text(_scene_yaml(source, opts))
            # into place: the photos, the config, then the params entry that makes DVC run the scene
            for tmp, final, move in ((raw_tmp, raw, os.rename), (conf_tmp, conf, os.link)):
                placed.append(final)  # before the move: a signal right after it must still undo it
                try:
                    move(tmp, final)  # os.link: fails rather than replace a config that appeared meanwhile
                except OSError:
                    placed.pop()  # not ours: never remove it
                    raise
            conf_tmp.unlink()
            _add_to_params(params, name)
        except BaseException as err:
            guard.disarm()
            _undo(raw_tmp, conf_tmp, params_tmp, placed, params, old_params, created)
            if isinstance(err, OSError):
                where = f" ({err.filename})" if err.filename else ""
                raise UsvcError(f"cannot add scene {name!r}: {err.strerror or err}{where}; nothing was "
                                "written") from None
            raise


def _undo(raw_tmp: Path, conf_tmp: Path, params_tmp: Path, placed: list[Path], params: Path, old_params: str,
          created: list[Path]) -> None:
    problems: list[str] = []

    def attempt(what: str, fn) -> None:
        try:
            fn()
        except FileNotFoundError:
            pass
        except OSError as e:
            problems.append(f"{what} ({e.strerror})")

    attempt(str(params), lambda: params.read_text() != old_params and _restore(params, old_params))
    for path in (params_tmp, conf_tmp, *placed, raw_tmp):
        if path.is_dir() and not path.is_symlink():
            attempt(str(path), lambda p=path: shutil.rmtree(p))
        else:
            attempt(str(path), lambda p=path: p.unlink())
    for folder in reversed(created):
        with contextlib.suppress(OSError):
            folder.rmdir()  # only if still empty
    if problems:
        log.error("could not undo everything; remove by hand: %s", ", ".join(problems[:SHOWN_PROBLEMS]))


def _restore(params: Path, text: str) -> None:
    tmp = params.with_name(params.name + ".restore")
    tmp.write_text(text)
    os.replace(tmp, params)


def add_scene(source: Path, checkout: Path, opts: NewSceneOptions) -> dict:
    """Check everything, then register data/raw/<name>, conf/scene/<name>.yaml and the params.yaml
    entry atomically; returns what was written."""
    check_options(opts)
    check_name(opts.name, checkout)
    source = Path(source).expanduser()
    if not source.is_dir():
        raise UsvcError(f"{source} is not a folder")
    source = source.resolve()
    tree = _scan_tree(source)
    scene = import_scene(opts.format, source, opts.name, "every_nth", opts.split_n, opts.metric_scale,
                         opts.exif_focal)
    _check_photos(scene, source, opts)
    _check_writable(checkout)
    with checkout_lock(checkout, LOCK_FILE):
        _check_free(opts.name, checkout)  # again: another `usvc map` may have taken it meanwhile
        _register(source, checkout, opts, tree)
    n_query = sum(f.split == "test" for f in scene.frames)
    raw, conf = checkout / "data" / "raw" / opts.name, checkout / "conf" / "scene" / f"{opts.name}.yaml"
    log.info("added scene %s: %d photos (%d queries) from %s", opts.name, len(scene.frames), n_query, source)
    return {"name": opts.name, "photos": len(scene.frames), "queries": n_query, "raw": str(raw),
            "config": str(conf), "has_poses": scene.has_poses}


def repro(checkout: Path, name: str) -> int:
    """``dvc repro metrics@<name>``: every stage the scene's metrics need, cached as usual."""
    dvc = shutil.which("dvc")
    if dvc is None:
        raise UsvcError("dvc is not on PATH (pip install -e . installs it)")
    cmd = [dvc, "repro", f"metrics@{name}"]
    log.info("running %s", " ".join(cmd))
    return subprocess.run(cmd, cwd=checkout, check=False).returncode
