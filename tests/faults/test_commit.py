"""Issue 25 D1: a commit is all or nothing, whatever instant it is interrupted at."""

from __future__ import annotations

from pathlib import Path

import pytest

from agents.training.commit import commit, committed, remove_leftovers


def _writer(text: str):
    return lambda f: f.write(text.encode())


def _files(tag: str) -> dict:
    return {
        name: _writer(f"{name} of {tag}") for name in ("checkpoint.pt", "replay.pt", "state.json")
    }


def _read(folder: Path) -> dict[str, str]:
    return {p.name: p.read_text() for p in folder.iterdir()}


class Killed(BaseException):
    """Stands in for a kill -9 between two writes."""


@pytest.mark.parametrize("dies_at", ["checkpoint.pt", "replay.pt", "state.json"])
def test_an_interrupted_commit_leaves_the_last_one_whole(tmp_path: Path, dies_at: str) -> None:
    commit(tmp_path, _files("a"))
    before = _read(committed(tmp_path))

    def die(f):
        raise Killed

    with pytest.raises(Killed):
        commit(tmp_path, {**_files("b"), dies_at: die})
    assert _read(committed(tmp_path)) == before
    after = commit(tmp_path, _files("c"))  # the next commit clears the torn attempt
    assert _read(committed(tmp_path))["state.json"] == "state.json of c"
    assert [p.name for p in (tmp_path / "commits").iterdir()] == [after.name]


def test_nothing_committed_and_a_corrupt_manifest(tmp_path: Path) -> None:
    assert committed(tmp_path) is None
    folder = commit(tmp_path, _files("a"))
    (folder / "replay.pt").unlink()
    with pytest.raises(ValueError, match=r"lacks replay\.pt"):
        committed(tmp_path)
    (tmp_path / "COMMIT").write_text("{not json")
    with pytest.raises(ValueError, match="corrupt commit manifest"):
        committed(tmp_path)


def test_leftover_temp_files_are_removed(tmp_path: Path) -> None:
    (tmp_path / ".checkpoint.pt.abc.tmp").write_bytes(b"torn")
    (tmp_path / "curves.csv").write_text("kept")
    remove_leftovers(tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["curves.csv"]
