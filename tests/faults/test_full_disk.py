"""Issue 25 fault suite: a full disk (a 64 KiB tmpfs, where this machine lets us mount one).
A write that does not fit raises, and what was written before stays whole."""

from __future__ import annotations

import errno
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from agents.training.commit import commit, committed
from mixed_traffic.provenance import read_records, write_record_atomic


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(disk)],
                             capture_output=True)  # fmt: skip
    if mounted.returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    try:
        yield disk
    finally:
        subprocess.run(["umount", str(disk)], check=True)


def test_a_record_that_does_not_fit_leaves_the_records_whole(small_disk: Path) -> None:
    path = small_disk / "records.jsonl"
    first = {"cell": {"seed": 0}, "status": "ok", "code": "c0de", "metrics": {"x": 1.0}}
    write_record_atomic(path, first)
    with pytest.raises(OSError) as err:
        write_record_atomic(path, {**first, "pad": "x" * 100_000})
    assert err.value.errno == errno.ENOSPC
    assert read_records(path) == [first]
    assert [p.name for p in small_disk.iterdir() if p.name.endswith(".tmp")] == []


def test_a_commit_that_does_not_fit_leaves_the_last_one(small_disk: Path) -> None:
    commit(
        small_disk, {"state.json": lambda f: f.write(b"{}"), "replay.pt": lambda f: f.write(b"1")}
    )
    before = committed(small_disk)
    big = {"state.json": lambda f: f.write(b"{}"), "replay.pt": lambda f: f.write(b"x" * 100_000)}
    with pytest.raises(OSError):
        commit(small_disk, big)
    assert committed(small_disk) == before and (before / "replay.pt").read_bytes() == b"1"
