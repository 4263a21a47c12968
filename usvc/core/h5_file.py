"""HDF5 artifacts in and out.

Reading: a missing, corrupt or incomplete file is one UsvcError naming it, never an h5py
traceback; so is a dataset whose header declares more data than the file can hold, refused before
anything is read or allocated (`check_declared_sizes`). Writing: the file is built in memory and
written to disk in one plain write, so a full disk, a file-size limit or a read-only folder is one
WriteError naming the destination, which the caller's atomic block cleans up after (HDF5 failing
mid-file floods stderr and can crash the interpreter).

Self-description: a writer passes its file's `format` name, `version` and a schema (dataset path
-> `Field`); every dataset in the file then carries `units`, `description` and, where it has
one, `frame` attributes, and a dataset the schema does not describe is a programming error
(ValueError) rather than an undocumented column. docs/artifacts.md lists the same fields.
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import h5py

from usvc.core.atomic import WRITE_ERRNOS, WriteError
from usvc.core.errors import UsvcError


@contextlib.contextmanager
def read_h5(path: str | Path, what: str) -> Iterator[h5py.File]:
    """`h5py.File(path, "r")`; errors while opening or reading inside the block name the file."""
    path = Path(path)
    if not path.is_file():
        raise UsvcError(f"{what} not found: {path}")
    try:
        h5 = h5py.File(path, "r")
    except OSError:
        raise UsvcError(f"{path}: cannot read {what}: not an HDF5 file, or corrupt or truncated") from None
    try:
        with h5:
            check_declared_sizes(h5, path, what)
            yield h5
    except UsvcError:
        raise
    except (KeyError, OSError, ValueError, TypeError, IndexError) as exc:
        detail = str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__
        raise UsvcError(f"{path}: {what} is incomplete or corrupt ({detail})") from None


# Deflate, HDF5's gzip filter, packs at most ~1032 bytes into one: a compressed dataset that declares
# more than this many times its stored bytes cannot hold what it declares.
MAX_COMPRESSION_RATIO = 1100


def _size(n: float) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} bytes"


def declared_size_problem(ds: h5py.Dataset, file_bytes: int) -> str:
    """Why `ds` cannot hold what its shape and type declare, from the HDF5 header alone ("" when it
    can): nothing is read or allocated. Contiguous (or compact) data must be stored whole, inside the
    file; chunked (compressed) data cannot expand beyond deflate's ratio, and its chunks must fit in
    the file. A crafted header (10^9 rows in a 10 MB file) is refused before numpy allocates for it."""
    shape = ds.shape
    if shape is None:  # a null dataspace: no data
        return ""
    elements = 1
    for n in shape:
        elements *= int(n)
    if elements == 0:
        return ""
    declared = elements * ds.id.get_type().get_size()  # the element's size in the file
    stored = ds.id.get_storage_size()
    what = (f"declares {'x'.join(map(str, shape)) or 'a scalar'} {ds.dtype} ({_size(declared)}), but the file "
            f"is {_size(file_bytes)}")
    if ds.external:
        return f"{what} and keeps it in external files: not a usvc artifact"
    if stored > file_bytes:
        return f"{what} and claims {_size(stored)} stored"
    if ds.chunks is None:
        if declared > stored:
            return f"{what} with {_size(stored)} stored"
    elif declared > max(stored, 1) * MAX_COMPRESSION_RATIO:
        return f"{what} with {_size(stored)} stored (more than compression can pack in it)"
    return ""


def check_declared_sizes(h5: h5py.File, path: Path, what: str) -> None:
    """Refuse a file any of whose datasets declares more data than the file can hold (one line naming
    the file and the dataset), before any dataset is read."""
    file_bytes = Path(path).stat().st_size
    found: list[tuple[str, str]] = []

    def visit(name: str, obj: object) -> None:
        if not found and isinstance(obj, h5py.Dataset):
            why = declared_size_problem(obj, file_bytes)
            if why:
                found.append((name, why))

    h5.visititems(visit)
    if found:
        name, why = found[0]
        raise UsvcError(f"{path}: {what} dataset {name} {why}: corrupt or crafted file")


@dataclass(frozen=True)
class Field:
    """What one dataset holds, written as its attributes.

    units: "px", "deg", "s", "scene units" (world length; times the scene's metric_scale gives
    metres), "1" (unitless: ratios, counts, indices, flags, names), or a short list where the
    columns differ (camera parameters).
    frame: "world", "camera", "image", or "A->B" for a transform from frame A to frame B; None
    where no frame applies (names, indices, features).
    """

    units: str
    description: str
    frame: str | None = None


# A schema maps a dataset's path in the file to its Field; "group/*" describes every dataset
# directly inside `group` (numbered datasets such as scene.h5's depth/<i>).
Schema = Mapping[str, Field]


def schema_field(schema: Schema, name: str) -> Field | None:
    """The Field of dataset `name` (a path inside the file, no leading slash), or None."""
    if name in schema:
        return schema[name]
    group = name.rsplit("/", 1)[0] if "/" in name else ""
    return schema.get(f"{group}/*" if group else "*")


def describe_datasets(h5: h5py.File, schema: Schema, where: str = "") -> None:
    """Write `units`, `description` (and `frame`) on every dataset of `h5` from `schema`."""
    datasets: list[str] = []
    h5.visititems(lambda name, obj: datasets.append(name) if isinstance(obj, h5py.Dataset) else None)
    undocumented = [name for name in datasets if schema_field(schema, name) is None]
    if undocumented:
        raise ValueError(f"{where or h5.filename}: dataset(s) {undocumented} missing from the writer's schema")
    for name in datasets:
        doc = schema_field(schema, name)
        assert doc is not None
        attrs = h5[name].attrs
        attrs["units"], attrs["description"] = doc.units, doc.description
        if doc.frame is not None:
            attrs["frame"] = doc.frame


@contextlib.contextmanager
def write_h5(path: str | Path, schema: Schema | None = None, file_format: str | None = None,
             version: int | None = None) -> Iterator[h5py.File]:
    """An in-memory HDF5 file that lands at `path` (normally a temporary path inside an atomic
    block) when the block succeeds.

    With `schema`, every dataset written in the block gets its attributes (`describe_datasets`)
    when the block ends; `file_format` and `version` become the file's `format` and `version`
    attributes.
    """
    buffer = io.BytesIO()
    with h5py.File(buffer, "w") as h5:
        yield h5
        if file_format is not None:
            h5.attrs["format"] = file_format
        if version is not None:
            h5.attrs["version"] = version
        if schema is not None:
            describe_datasets(h5, schema, str(path))
    write_bytes(Path(path), buffer.getbuffer())


def write_bytes(path: Path, data: bytes | memoryview) -> None:
    """Write a whole file; no space, a file-size limit, a read-only disk or no permission is a
    WriteError (a UsvcError) naming the file's destination (not its temporary path) and the reason."""
    try:
        with open(path, "wb") as f:
            f.write(data)
    except OSError as exc:
        if exc.errno in WRITE_ERRNOS:
            with contextlib.suppress(OSError):
                Path(path).unlink(missing_ok=True)
            raise WriteError(path, exc) from None
        raise
