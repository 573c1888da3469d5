"""evaluate CLI (real SUMO), its argument errors, and the atomic JSON-lines record file."""

from __future__ import annotations

import json
import multiprocessing as mp
import subprocess
import sys
from pathlib import Path

import pytest

from mixed_traffic.experiments.evaluate import main
from mixed_traffic.provenance import read_records, scan_records, write_record_atomic
from mixed_traffic.schema import METRICS

REPO = Path(__file__).resolve().parents[1]


def test_cli_json_record(tmp_path: Path) -> None:
    out = tmp_path / "records.jsonl"
    cmd = [sys.executable, "-m", "mixed_traffic.evaluate", "--policy", "idm",
           "--scenario", "straight", "--density", "60", "--penetration", "0",
           "--episode-length", "60", "--warmup", "10", "--out", str(out), "--json",
           "--no-progress"]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=120)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 1
    rec = json.loads(lines[0])
    assert rec["status"] == "ok"
    assert rec["config"]["scenario"] == "straight" and rec["config"]["density"] == 60.0
    assert rec["config"]["penetration"] == 0.0 and rec["seed"] == 0
    assert rec["cell"] == {"policy": "idm", "scenario": "straight", "density": 60.0,
                           "penetration": 0.0, "weather": "normal", "detection_range": 1.0, "seed": 0,
                           "copy": 0}  # fmt: skip
    assert rec["sumo_version"].startswith("1.28")
    assert rec["git_revision"] and rec["git_revision"] != "unknown"
    m = rec["metrics"]
    assert set(m) == set(METRICS)
    assert m["measured_density"] == pytest.approx(60.0, rel=0.15)
    assert 30.0 < m["dt_tf"] < 80.0  # 1 km at 12.5-33 m/s
    assert m["collisions"] == 0 and m["teleports"] == 0
    # the same record was appended to --out, and the table went to stderr
    assert read_records(out) == [rec]
    assert "DT-TF" in proc.stderr


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--density", "-5"], "density"),
        (["--density", "5000"], "density"),
        (["--penetration", "1.5"], "penetration"),
        (["--scenario", "no_such_road"], "no_such_road"),
        (["--warmup", "500"], "warmup"),
        (["--seeds", "-1"], "seed"),
        (["--density", "abc"], "--density"),
        (["--policy", "nope"], "--policy"),
    ],
)
def test_bad_arguments_exit_2_naming_the_field(args, needle, capsys, tmp_path) -> None:
    with pytest.raises(SystemExit) as exc:
        main([*args, "--out", str(tmp_path / "r.jsonl")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err
    assert not (tmp_path / "r.jsonl").exists()


def test_records_survive_a_truncated_line(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "records.jsonl"
    for i in range(3):
        write_record_atomic(path, {"seed": i, "metrics": {"dt_tf": 40.0 + i, "x": float("nan")}})
    assert [r["seed"] for r in read_records(path)] == [0, 1, 2]
    assert read_records(path)[0]["metrics"]["x"] is None  # NaN is stored as null
    # a crashed foreign writer left half a line
    with open(path, "a") as fh:
        fh.write('{"seed": 99, "metr')
    with pytest.warns(RuntimeWarning, match="truncated"):
        assert [r["seed"] for r in read_records(path)] == [0, 1, 2]
    write_record_atomic(path, {"seed": 3})
    records, bad = scan_records(path)
    assert [r["seed"] for r in records] == [0, 1, 2, 3]
    assert bad == [4]
    # a record that cannot be serialised raises before the file is touched
    before = path.read_bytes()
    with pytest.raises(TypeError):
        write_record_atomic(path, {"seed": object()})
    assert path.read_bytes() == before
    assert not [p for p in path.parent.iterdir() if p.name.endswith(".tmp")]


def _writer(args: tuple[str, int]) -> None:
    path, worker = args
    for i in range(15):
        write_record_atomic(path, {"worker": worker, "i": i, "pad": "x" * 2000})


def test_concurrent_writers_lose_nothing(tmp_path: Path) -> None:
    path = tmp_path / "records.jsonl"
    with mp.get_context("fork").Pool(4) as pool:
        pool.map(_writer, [(str(path), w) for w in range(4)])
    records, bad = scan_records(path)
    assert bad == []
    assert sorted((r["worker"], r["i"]) for r in records) == [
        (w, i) for w in range(4) for i in range(15)
    ]
