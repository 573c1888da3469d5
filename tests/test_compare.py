"""Checkpoint comparison on the train split (mixed_traffic.experiments.compare), on real SUMO."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.checkpoint import load_checkpoint, save_checkpoint
from mixed_traffic.experiments.compare import (
    CompareConfig,
    expand,
    main,
    rank,
    rank_key,
    run,
    score,
)
from mixed_traffic.provenance import code_key, read_records

SHIPPED = Path(__file__).resolve().parents[1] / "agents" / "checkpoints" / "auto.pt"


def _run_folder(tmp: Path) -> Path:
    """A training-run layout: auto.pt (the shipped network) and one perturbed snapshot."""
    run_dir = tmp / "run"
    (run_dir / "snapshots").mkdir(parents=True)
    shutil.copy(SHIPPED, run_dir / "auto.pt")
    learner, meta = load_checkpoint(SHIPPED)
    torch.manual_seed(0)
    with torch.no_grad():
        for p in learner.actor.parameters():
            p.add_(0.05 * torch.randn_like(p))
    save_checkpoint(run_dir / "snapshots" / "000001000.pt", learner, meta)
    return run_dir


def test_checkpoints_are_ranked_by_their_excess_over_the_tuned_rule(tmp_path: Path) -> None:
    run_dir = _run_folder(tmp_path)
    checkpoints = expand([run_dir])
    assert [c.name for c in checkpoints] == ["000001000.pt", "auto.pt"]
    cfg = CompareConfig(scenarios=("straight-3lane",), density=60.0, penetrations=(1.0,),
                        seeds=(100,), episode_length=30.0, warmup=2.0, out=tmp_path / "cmp")  # fmt: skip
    scores = run(cfg, checkpoints, progress=False)
    assert sorted(s["checkpoint"] for s in scores) == sorted(map(str, checkpoints))

    def dt_a(key: str) -> float:
        (rec,) = read_records(cfg.folder / key / "straight-3lane" / "records.jsonl")
        assert rec["status"] == "ok" and rec["cell"]["seed"] == 100
        return rec["metrics"]["avg_dt_a"]

    for s in scores:  # recomputed from the records on disk
        assert s["unsafe"] == 0
        assert s["max_excess"] == pytest.approx(100 * (dt_a(s["key"]) / dt_a(cfg.baseline) - 1))
    assert scores[0]["max_excess"] <= scores[1]["max_excess"]
    assert scores[0]["key"] != scores[1]["key"]  # different weights, different records

    assert cfg.folder.name == f"code-{code_key()}"  # a code change starts a new cache
    files = sorted(cfg.folder.rglob("records.jsonl"))
    before = [f.read_bytes() for f in files]
    assert run(cfg, checkpoints, progress=False) == scores  # resumed: nothing re-run
    assert [f.read_bytes() for f in files] == before


def _cells(dt: dict[tuple[str, float], float], terminal: int = 0) -> dict:
    return {k: {"avg_dt_a": v, "terminal": terminal, "failed": 0} for k, v in dt.items()}


def test_score_takes_the_largest_excess_and_puts_unsafe_checkpoints_last() -> None:
    acc = _cells({("a", 0.2): 100.0, ("b", 1.0): 200.0})
    even = score(_cells({("a", 0.2): 101.0, ("b", 1.0): 202.0}), acc)
    lopsided = score(_cells({("a", 0.2): 90.0, ("b", 1.0): 210.0}), acc)
    unsafe = score(_cells({("a", 0.2): 80.0, ("b", 1.0): 160.0}, terminal=1), acc)
    missing = score(_cells({("a", 0.2): 80.0}), acc)
    assert even["max_excess"] == pytest.approx(1.0)
    assert lopsided["max_excess"] == pytest.approx(5.0)
    assert lopsided["mean_excess"] == pytest.approx(np.mean([-10.0, 5.0]))
    assert unsafe["unsafe"] == 2 and missing["unsafe"] == 1 and math.isnan(missing["max_excess"])
    ranked = sorted([missing, unsafe, lopsided, even], key=rank_key)
    assert ranked == [even, lopsided, unsafe, missing]  # unsafe last, however fast


def test_near_ties_in_the_largest_excess_go_to_the_lower_mean() -> None:
    acc = _cells({("a", 0.2): 100.0, ("b", 1.0): 100.0, ("c", 1.0): 100.0})
    flat = score(_cells({("a", 0.2): 100.2, ("b", 1.0): 99.0, ("c", 1.0): 99.0}), acc)
    lower = score(_cells({("a", 0.2): 100.3, ("b", 1.0): 97.0, ("c", 1.0): 97.0}), acc)
    far = score(_cells({("a", 0.2): 101.0, ("b", 1.0): 90.0, ("c", 1.0): 90.0}), acc)
    unsafe = score(_cells({("a", 0.2): 90.0, ("b", 1.0): 90.0, ("c", 1.0): 90.0}, 1), acc)
    scores = [unsafe, far, flat, lower]
    assert rank(scores, tie=0.0) == [flat, lower, far, unsafe]  # strict largest-excess order
    assert rank(scores, tie=0.5) == [lower, flat, far, unsafe]  # 0.1 apart: the mean decides
    assert rank(scores, tie=2.0) == [far, lower, flat, unsafe]  # never an unsafe one
    assert rank([unsafe], tie=0.5) == [unsafe] and rank([], tie=0.5) == []


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        ([str(SHIPPED), "--scenarios", "straight-eval"], "held-out"),
        (["no/such/run"], "no such checkpoint"),
        ([str(SHIPPED), "--warmup", "90"], "--warmup"),
        ([str(SHIPPED), "--tie", "-1"], "--tie"),
    ],
)
def test_bad_arguments_exit_with_a_clear_message(argv: list[str], message: str, capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_an_unreadable_checkpoint_is_named_before_any_episode(tmp_path: Path, capsys) -> None:
    """Issue 25 D9: it used to rank best (all its cells failed, so nothing was in excess)."""
    bad = tmp_path / "torn.pt"
    bad.write_bytes(SHIPPED.read_bytes()[:5000])
    with pytest.raises(SystemExit) as exit_info:
        main([str(SHIPPED), str(bad), "--out", str(tmp_path / "cmp")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "torn.pt: corrupt or unreadable" in err
    assert not (tmp_path / "cmp").exists()


def test_code_key_follows_sources_checkpoint_and_scenarios_only(tmp_path: Path) -> None:
    root, scen = tmp_path / "repo", tmp_path / "scenarios"
    for path, text in [(root / "mixed_traffic" / "env.py", "a = 1\n"),
                       (root / "agents" / "acc_lc.py", "b = 2\n"),
                       (root / "agents" / "checkpoints" / "auto.pt", "weights"),
                       (scen / "straight" / "net.xml", "<net/>\n")]:  # fmt: skip
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    key = code_key(root, scen)
    (root / "README.md").write_text("docs\n")
    (root / "agents" / "notes.txt").write_text("not code\n")
    assert code_key(root, scen) == key
    (root / "agents" / "acc_lc.py").write_text("b = 3\n")
    changed = code_key(root, scen)
    assert changed != key
    (scen / "straight" / "net.xml").write_text("<net version='2'/>\n")
    keys = {key, changed, code_key(root, scen)}
    (root / "agents" / "checkpoints" / "auto.pt").write_text("other weights")
    keys.add(code_key(root, scen))
    assert len(keys) == 4
