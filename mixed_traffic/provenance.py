"""Where a result came from (config, seed, SUMO version, git revision) and safe record files.

Records are JSON lines (one episode per line, layout in ``schema``). ``write_record_atomic``
never leaves a partial line and never loses an existing record: under an exclusive lock it
writes the old content plus the new line to a temporary file in the same folder, fsyncs it and
``os.replace``\\ s it over the original, so a crash at any point leaves either the old or the new
file. ``read_records`` skips (and reports) lines that are not complete JSON objects, e.g. a
truncated last line left by some other writer.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import hashlib
import json
import math
import os
import subprocess
import sys
import tempfile
import warnings
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

from mixed_traffic.config import EnvConfig
from mixed_traffic.paths import REPO_ROOT, SCENARIOS_DIR
from mixed_traffic.world.backend import sumo_version as _backend_sumo_version


def git_revision(repo: Path = REPO_ROOT) -> str:
    """Short commit hash of ``repo``, with ``-dirty`` if tracked files changed; ``unknown`` outside git."""
    try:
        rev = subprocess.run(
            ["git", "-C", str(repo), "rev-parse", "--short", "HEAD"],
            capture_output=True, text=True, timeout=10, check=True,
        ).stdout.strip()  # fmt: skip
        status = subprocess.run(
            ["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=10, check=True,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if not rev:
        return "unknown"
    return f"{rev}-dirty" if status else rev


def code_key(root: Path = REPO_ROOT, scenarios: Path = SCENARIOS_DIR) -> str:
    """Hash (12 hex digits) of what decides an episode besides its config: the Python sources
    of ``mixed_traffic`` and ``agents``, the shipped checkpoint and the scenario files. Unlike
    the git revision it changes with uncommitted edits and not with documentation."""
    files = [(root, f) for d in ("mixed_traffic", "agents") for f in (root / d).rglob("*.py")]
    files += [(root, f) for f in (root / "agents" / "checkpoints").glob("*.pt")]
    files += [(scenarios, f) for f in scenarios.rglob("*") if f.is_file()]
    h = hashlib.sha256()
    for base, f in sorted(files, key=lambda bf: str(bf[1].relative_to(bf[0]))):
        h.update(str(f.relative_to(base)).encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:12]


def file_digest(path: str | Path) -> str:
    """SHA-256 (12 hex digits) of a file's bytes, e.g. the weights a record's policy ran."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:12]


@functools.cache
def current_code_key() -> str:
    """``code_key`` of this process's code, taken once (edits after import do not run)."""
    return code_key()


def sumo_version() -> str:
    """Version of the SUMO binaries in use (the backend's answer)."""
    return _backend_sumo_version()


def now_iso() -> str:
    """Current UTC time, ISO 8601 with seconds."""
    return datetime.now(UTC).isoformat(timespec="seconds")


def record_meta(config: EnvConfig) -> dict[str, Any]:
    """Provenance fields of a record: config (nested dict), seed, SUMO version, git revision,
    code hash (``code_key``), created."""
    return {
        "config": config.to_dict(),
        "seed": config.seed,
        "sumo_version": sumo_version(),
        "git_revision": git_revision(),
        "code": current_code_key(),
        "created": now_iso(),
    }


def json_safe(value: Any) -> Any:
    """``value`` with NaN/inf floats turned into None and numpy scalars/arrays into plain Python."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        return json_safe(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def record_line(record: dict[str, Any]) -> str:
    """One record as a single JSON line (no trailing newline); raises before any file is touched."""
    line = json.dumps(json_safe(record), allow_nan=False, ensure_ascii=False)
    if "\n" in line:  # json.dumps escapes newlines in strings; this is a guard only
        raise ValueError("record serialises to more than one line")
    return line


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """Exclusive advisory lock on ``<path>.lock`` (the data file itself is replaced, so not it)."""
    lock = path.with_name(path.name + ".lock")
    with open(lock, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


class FolderBusyError(RuntimeError):
    """Another live process is running into the same results folder."""


@contextlib.contextmanager
def exclusive_folder(folder: Path) -> Iterator[None]:
    """Hold ``folder``'s run lock (``.run.lock``, released by the OS even on kill -9), so two
    runs never execute the same cells at once; FolderBusyError names the holder otherwise."""
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / ".run.lock", "a+") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip() or "unknown"
            raise FolderBusyError(
                f"{folder} is in use by another run (pid {holder}); wait for it to finish or "
                "pass another --out"
            ) from None
        fh.seek(0)
        fh.truncate()
        fh.write(str(os.getpid()))
        fh.flush()
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def check_writable(path: str | Path, what: str = "records") -> None:
    """Raise ``ValueError`` naming ``path`` unless ``what`` (records, a report, a GIF) can be
    written there (its folder is created); call it before any work starts, so that no result is
    lost at the end."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path} is a folder, not a {what} file")
    blocking = next((p for p in path.parents if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise ValueError(f"cannot write {what} to {path}: {blocking} is a file, not a folder")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", suffix=".probe"):
            pass
    except OSError as e:
        raise ValueError(f"cannot write {what} to {path}: {e.strerror or e}") from None


def check_folder(path: str | Path) -> None:
    """Raise ``ValueError`` naming ``path`` if a file stands where it or one of its parents
    must be a folder (an output folder; nothing is created)."""
    path = Path(path)
    blocking = next((p for p in (path, *path.parents) if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise ValueError(f"cannot use {path} as a folder: {blocking} is a file, not a folder")


def write_record_atomic(path: str | Path, record: dict[str, Any]) -> None:
    """Append ``record`` as one JSON line to ``path`` atomically (see module docstring).

    The folder is created if needed. Concurrent writers (processes) are serialised by a lock
    file next to ``path``. A truncated last line already in the file is kept as it is (and
    terminated by a newline) so that ``read_records`` can flag it; it never swallows the new
    record.
    """
    path = Path(path)
    line = record_line(record).encode("utf-8") + b"\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    with _locked(path):
        old = path.read_bytes() if path.exists() else b""
        if old and not old.endswith(b"\n"):
            old += b"\n"
        atomic_write(path, lambda fh: fh.write(old + line))


def rewrite_records(path: str | Path, records: list[dict[str, Any]]) -> None:
    """Replace ``path`` by exactly ``records`` (one JSON line each), atomically and locked."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with _locked(path):
        data = b"".join(record_line(r).encode("utf-8") + b"\n" for r in records)
        atomic_write(path, lambda fh: fh.write(data))


def atomic_write(path: Path, writer: Callable[[IO[bytes]], Any]) -> None:
    """``writer(file)`` into a temp file beside ``path``, fsync, keep the mode, ``os.replace``,
    fsync the folder: a crash mid-write leaves the previous file whole."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            writer(fh)
            fh.flush()
            os.fsync(fh.fileno())
        mode = path.stat().st_mode & 0o777 if path.exists() else 0o666 & ~_umask()
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    fsync_dir(path.parent)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def fsync_dir(folder: Path) -> None:
    """Make a rename inside ``folder`` durable (where the platform allows it)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def scan_records(path: str | Path) -> tuple[list[dict[str, Any]], list[int]]:
    """All complete records of a JSON-lines file, and the 1-based numbers of unreadable lines."""
    path = Path(path)
    if not path.exists():
        return [], []
    records: list[dict[str, Any]] = []
    bad: list[int] = []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for no, raw in enumerate(fh, start=1):
            text = raw.strip()
            if not text:
                continue
            try:
                obj = json.loads(text)
            except json.JSONDecodeError:
                bad.append(no)
                continue
            if isinstance(obj, dict):
                records.append(obj)
            else:
                bad.append(no)
    return records, bad


def read_records(path: str | Path) -> list[dict[str, Any]]:
    """Complete records of ``path`` (empty if it does not exist); warns about skipped lines."""
    records, bad = scan_records(path)
    if bad:
        warnings.warn(
            f"{path}: skipped {len(bad)} unreadable line(s) {bad[:10]} (truncated or corrupt); "
            f"{len(records)} complete record(s) kept",
            RuntimeWarning,
            stacklevel=2,
        )
    return records


def records_of_this_code(path: Path) -> list[dict]:
    """The records in ``path`` written by this code. Those of other code (another ``code``
    hash, or none) would count as done and mix into the report, so they move to
    ``records.code-<theirs>.jsonl`` (written before ``path`` is rewritten: nothing is lost)."""
    records, ours = read_records(path), current_code_key()
    keep = [r for r in records if r.get("code") == ours]
    if len(keep) == len(records):
        return records
    others = [r for r in records if r.get("code") != ours]
    tag = "-".join(sorted({str(r.get("code") or "unknown") for r in others}))[:40]
    aside, n = path.with_name(f"records.code-{tag}.jsonl"), 1
    while aside.exists():
        n += 1
        aside = path.with_name(f"records.code-{tag}.{n}.jsonl")
    rewrite_records(aside, others)
    rewrite_records(path, keep)
    print(f"{path}: {len(others)} record(s) of other code ({tag}) moved to {aside.name}; "
          f"{len(keep)} kept", file=sys.stderr)  # fmt: skip
    return keep
