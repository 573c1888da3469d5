"""A training run's state committed as one unit, like a database's write-ahead commit.

Each commit writes its files into ``out/commits/<name>.tmp``, fsyncs them, renames the folder to
``out/commits/<name>`` and only then replaces the manifest ``out/COMMIT`` (the commit point),
before older commits are removed. A kill -9 at any instant therefore leaves the last committed
set whole: checkpoint, replay and counters always belong together.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from mixed_traffic.provenance import atomic_write, fsync_dir

MANIFEST = "COMMIT"
FOLDER = "commits"

Writer = Callable[[BinaryIO], object]


def committed(out: Path) -> Path | None:
    """The folder of ``out``'s last commit, or None when nothing was ever committed.

    ValueError naming the file when the manifest or a file it lists is unreadable or missing.
    """
    manifest = out / MANIFEST
    if not manifest.is_file():
        return None
    try:
        entry = json.loads(manifest.read_text())
        folder, files = out / FOLDER / entry["commit"], entry["files"]
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{manifest}: corrupt commit manifest ({exc})") from exc
    missing = [f for f in files if not (folder / f).is_file()]
    if missing:
        raise ValueError(f"{manifest}: commit {folder.name} lacks {', '.join(missing)}")
    return folder


def commit(out: Path, files: dict[str, Writer]) -> Path:
    """Write ``files`` (name → writer of its bytes) as ``out``'s new commit; its folder."""
    last = committed(out)
    number = int(last.name) + 1 if last is not None else 1
    root = out / FOLDER
    final, tmp = root / f"{number:06d}", root / f"{number:06d}.tmp"
    for stale in (final, tmp):  # an earlier, uncommitted attempt at this number
        shutil.rmtree(stale, ignore_errors=True)
    tmp.mkdir(parents=True)
    for name, writer in files.items():
        with (tmp / name).open("wb") as f:
            writer(f)
            f.flush()
            os.fsync(f.fileno())
    fsync_dir(tmp)
    os.replace(tmp, final)
    fsync_dir(root)
    entry = {"commit": final.name, "files": sorted(files)}
    atomic_write(out / MANIFEST, lambda f: f.write(json.dumps(entry).encode()))
    fsync_dir(out)
    for old in root.iterdir():
        if old != final:
            shutil.rmtree(old, ignore_errors=True)
    return final


def remove_leftovers(out: Path) -> None:
    """Delete temp files that a killed atomic write left in ``out`` (``.<name>.*.tmp``)."""
    for tmp in out.glob(".*.tmp"):
        tmp.unlink(missing_ok=True)
