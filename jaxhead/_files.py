"""Atomic file writes and content digests, used by every writer in jaxhead.  [host]"""

import contextlib
import csv
import hashlib
import os
import secrets
from collections.abc import Iterable, Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_write_path(path: str | os.PathLike, *, fsync: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success rename it onto `path`, else delete it.

    The temporary name is ``.tmp-<random>-<name>``: hidden, in the same directory (so
    ``os.replace`` is an atomic rename on POSIX and Windows), and ending with the target's
    full name so that writers choosing the format by extension (nibabel's ``.nii.gz``,
    meshio, trimesh, matplotlib) see the right one. The file is not created in advance; the
    writer creates it (with the usual permissions). An existing `path` is replaced only after
    the block finished without an exception; if it raised, `path` is untouched.

    Arguments:
        path: the final file path; its directory must exist.
        fsync: flush the temporary file to disk before the rename, so that a crash right after
            it cannot leave an empty file under the final name.

    Yields:
        the temporary path to write to.
    """
    path = Path(path)
    parent = path.parent
    if not parent.is_dir():
        raise FileNotFoundError(
            f"cannot write {str(path)!r}: directory {str(parent)!r} does not exist; "
            "create it first."
        )
    if path.is_dir():
        raise ValueError(f"cannot write {str(path)!r}: it is a directory; pass a file path.")
    tmp = parent / f".tmp-{secrets.token_hex(6)}-{path.name}"
    try:
        yield tmp
        if not tmp.exists():
            raise FileNotFoundError(
                f"the writer for {str(path)!r} did not create its temporary file {str(tmp)!r}; "
                "write to the path yielded by atomic_write_path."
            )
        if fsync:
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_csv(path: str | os.PathLike, columns, rows: Iterable[dict]) -> None:
    """A CSV table written atomically: a header of `columns`, then one line per row dict
    (keys not in `columns` are left out, missing ones are empty)."""
    with atomic_write_path(path) as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(columns), extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)


def file_digest(path: str | os.PathLike) -> str:
    """The sha256 hex digest of a file's content, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
