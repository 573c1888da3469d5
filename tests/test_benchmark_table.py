"""The benchmark table (python -m mixed_traffic.benchmark) on real SUMO: one task, short
episodes, a resumed re-run and bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from pypdf import PdfReader

from analysis.benchmark_report import TABLE_BEGIN, TABLE_END
from mixed_traffic import paths
from mixed_traffic.benchmark import table
from mixed_traffic.benchmark.score import uniform_flow_speed
from mixed_traffic.provenance import read_records


def test_the_table_scores_a_task_and_a_rerun_runs_nothing(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    out = tmp_path / "records.jsonl"
    argv = ["--tasks", "ring", "--policies", "follower-stopper", "--seeds", "0", "1",
            "--episode-length", "20", "--out", str(out), "--runs", str(tmp_path / "no-runs")]  # fmt: skip
    assert table.main(argv) == 0
    assert "| ring-v2 | follower-stopper |" in (tmp_path / "table.md").read_text()
    pdf = "".join(p.extract_text() for p in PdfReader(tmp_path / "benchmark.pdf").pages)
    assert "ring-v2" in pdf and "follower-stopper" in pdf
    assert (tmp_path / "benchmark-scores.png").is_file()
    # --update-reference: the page's table and the reference report, in a checkout of our own
    checkout = tmp_path / "checkout"
    (checkout / "docs").mkdir(parents=True)
    (checkout / "reports").mkdir()
    page = checkout / "docs" / "benchmark.md"
    page.write_text(f"# x\n{TABLE_BEGIN}\nold\n{TABLE_END}\nafter\n")
    monkeypatch.setattr(paths, "REPO_ROOT", checkout)
    assert table.main([*argv, "--update-reference"]) == 0  # resumes: no episode runs again
    text = page.read_text()
    assert "old" not in text and "| ring-v2 | follower-stopper |" in text and "after" in text
    assert (checkout / "reports" / "benchmark.pdf").is_file()
    records = read_records(out)
    assert len(records) == 2 * 2 * 2  # eval configs x (idm, follower-stopper) x seeds
    rows = json.loads((tmp_path / "scores.json").read_text())
    by = {r["policy"]: r for r in rows}
    assert set(by) == {"idm", "follower-stopper"} and by["idm"]["score"] == 0.0
    cfg = table.BenchmarkConfig(tasks=("ring-v2",), policies=("follower-stopper",), seeds=(0, 1),
                                episode_length=20.0, out=out)  # fmt: skip
    recs = table.run_table(cfg, progress=False)  # nothing left to run: the same records
    assert len(read_records(out)) == 8
    refs = [uniform_flow_speed(c, c.ring_length[0]) for c in table.TASKS["ring-v2"].eval]
    assert by["idm"]["references"] == pytest.approx(refs)
    human = [
        recs[("ring-v2", i, "idm", s, 20.0, 0, 1)]["metrics"]["mean_speed"]
        for i in (0, 1)
        for s in (0, 1)
    ]
    fs = [recs[("ring-v2", i, "follower-stopper", s, 20.0, 0, 1)]["metrics"]["mean_speed"]
          for i in (0, 1) for s in (0, 1)]  # fmt: skip
    expected = [
        ((fs[2 * i + s] - human[2 * i + s]) / (refs[i] - human[2 * i + s]))
        for i in (0, 1)
        for s in (0, 1)
    ]
    assert by["follower-stopper"]["score"] == pytest.approx(sum(expected) / 4)
    assert "| ring-v2 | follower-stopper |" in capsys.readouterr().out


@pytest.mark.parametrize(("argv", "needle"), [
    (["--policies", "magic"], "policy 'magic' is not available"),
    (["--tasks", "figure-eight"], "unknown benchmark task 'figure-eight'"),
    (["--seeds", "-1"], "--seeds=[-1]: give seeds >= 0"),
])  # fmt: skip
def test_bad_input_is_one_line_before_any_episode(argv, needle, tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        table.main([*argv, "--out", str(tmp_path / "r.jsonl")])
    assert stop.value.code == 2 and needle in capsys.readouterr().err
    assert not (tmp_path / "r.jsonl").exists()
