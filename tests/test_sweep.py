"""Sweeps end to end on real SUMO: records, figures and a PDF; resume after a kill; bad args."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from pypdf import PdfReader

from agents.policies import SHIPPED_CHECKPOINT
from mixed_traffic.experiments.sweep import SweepConfig, cells, main, parse_args
from mixed_traffic.provenance import current_code_key, exclusive_folder, read_records

TINY = [
    "--values",
    "0.5",
    "--policies",
    "random",
    "--seeds",
    "0",
    "--episode-length",
    "60",
    "--warmup",
    "5",
]


def _pdf_text(path: Path) -> str:
    return "\n".join(page.extract_text() for page in PdfReader(path).pages)


def test_tiny_sweep_writes_records_figures_and_report(tmp_path: Path) -> None:
    out, pdf = tmp_path / "res", tmp_path / "rep.pdf"
    assert (
        main(["--penetration", *TINY, "--at-density", "60", "--out", str(out), "--pdf", str(pdf)])
        == 0
    )
    records = read_records(out / "records.jsonl")
    assert sorted(r["cell"]["policy"] for r in records) == ["idm", "random"]
    assert all(r["status"] == "ok" for r in records), [r.get("error") for r in records]
    for r in records:
        assert r["sumo_version"] and r["git_revision"] and r["config"]["density"] == 60.0
    idm = next(r for r in records if r["cell"]["policy"] == "idm")
    assert idm["cell"]["penetration"] == 0.0
    dt_tf = idm["metrics"]["dt_tf"]
    assert dt_tf is not None and 35 < dt_tf < 60  # 1 km at roughly 24 m/s free flow
    assert list(tmp_path.glob("rep-*.png")), "figures are written beside the report"
    text = _pdf_text(pdf)
    for name in (
        "DT-TF",
        "AvgDT-A",
        "MinTTC-A",
        "collisions",
        "SUMO version",
        records[0]["git_revision"],
    ):
        assert name in text, name
    assert f"{dt_tf:.2f}" in text  # the reference's DT-TF appears as the report formats it
    # the traffic figures: all-human cells over densities and two cells' trajectories
    fd = read_records(out / "fd" / "records.jsonl")
    assert {r["cell"]["density"] for r in fd} == {36.0, 60.0, 84.0, 108.0, 132.0, 156.0, 180.0}
    assert all(r["cell"]["policy"] == "idm" and r["metrics"]["flow"] > 0 for r in fd)
    traces = sorted(p.name for p in (out / "trajectories").glob("*.npz"))
    assert traces == ["idm-penetration-0.0-seed0.npz", "random-penetration-0.5-seed0.npz"]
    for section in ("Fundamental diagram", "Space-time diagram"):
        assert section in text, section


def test_interrupted_sweep_resumes_without_duplicates(tmp_path: Path) -> None:
    out = tmp_path / "res"
    args = [sys.executable, "-m", "mixed_traffic.sweep", "--penetration", "--values", "0.3", "0.6",
            "--policies", "random", "--seeds", "0", "--episode-length", "20", "--warmup", "2",
            "--workers", "1", "--no-report", "--no-traffic", "--out", str(out)]  # fmt: skip
    proc = subprocess.Popen(
        args, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    records_file = out / "records.jsonl"
    deadline = time.time() + 120
    while time.time() < deadline and not (records_file.exists() and read_records(records_file)):
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)  # the sweep and its worker die mid-run
    proc.wait()
    first = read_records(records_file)
    assert 1 <= len(first) < 3
    subprocess.run(
        args, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=300
    )
    records = read_records(records_file)
    keys = [json.dumps(r["cell"], sort_keys=True) for r in records]
    assert len(keys) == len(set(keys)) == 3  # idm reference + 2 penetrations, each once
    assert all(r["status"] == "ok" for r in records)
    assert all(r in records for r in first)  # kept, not run again


def test_a_second_run_into_a_busy_folder_stops_before_any_cell(tmp_path: Path, capsys) -> None:
    """Issue 25 D12: two concurrent runs used to execute the same cells twice."""
    out = tmp_path / "res"
    args = ["--penetration", "--values", "0.5", "--policies", "random", "--seeds", "0",
            "--episode-length", "10", "--warmup", "1", "--no-report", "--no-traffic",
            "--no-reference", "--out", str(out)]  # fmt: skip
    with exclusive_folder(out):  # as if another sweep were running into out
        assert main(args) == 2
    assert f"in use by another run (pid {os.getpid()})" in capsys.readouterr().err
    assert read_records(out / "records.jsonl") == []
    assert main(args) == 0 and len(read_records(out / "records.jsonl")) == 1


def test_records_from_other_code_are_set_aside_and_run_again(tmp_path: Path) -> None:
    out = tmp_path / "res"
    args = ["--penetration", "--values", "0.5", "--policies", "random", "--seeds", "0",
            "--episode-length", "10", "--warmup", "1", "--no-report", "--no-traffic", "--no-reference",
            "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    (record,) = read_records(out / "records.jsonl")
    assert record["code"] == current_code_key()
    old = {**record, "code": "0123456789ab", "metrics": {}}  # as if an older env wrote it
    (out / "records.jsonl").write_text(json.dumps(old) + "\n")
    assert main(args) == 0
    assert read_records(out / "records.code-0123456789ab.jsonl") == [old]
    (again,) = read_records(out / "records.jsonl")
    assert again["code"] == current_code_key()
    assert again["metrics"]["avg_vel_a"] == record["metrics"]["avg_vel_a"]  # same seed, re-run
    # D8: one record without a code moves aside alone; this code's records stay done
    stray = {k: v for k, v in old.items() if k != "code"}
    (out / "records.jsonl").write_text(json.dumps(again) + "\n" + json.dumps(stray) + "\n")
    assert main(args) == 0
    assert read_records(out / "records.jsonl") == [again]  # not run again
    assert read_records(out / "records.code-unknown.jsonl") == [stray]


def test_failed_cell_is_recorded_and_the_sweep_goes_on(tmp_path: Path) -> None:
    out = tmp_path / "res"
    # readable, but made for a 2-step history: the cell fails when its env (history 5) starts
    odd = tmp_path / "other_history.pt"
    data = torch.load(SHIPPED_CHECKPOINT, weights_only=True)
    data["meta"]["lca"]["z"] = data["meta"]["lca"]["z"] + 3
    torch.save(data, odd)
    args = ["--penetration", "--values", "0.5", "--policies", "auto", "random", "--seeds", "0",
            "--episode-length", "10", "--warmup", "1", "--no-report", "--no-traffic",
            "--no-reference", "--checkpoint", str(odd), "--out", str(out)]  # fmt: skip
    assert main(args) == 1  # a failed cell is an error exit, with a summary line
    records = {r["cell"]["policy"]: r for r in read_records(out / "records.jsonl")}
    assert records["auto"]["status"] == "failed" and "other_history" in records["auto"]["error"]
    assert records["random"]["status"] == "ok"
    # a re-run retries the failed cell, not the finished one
    assert main(args) == 1
    runs = [r["cell"]["policy"] for r in read_records(out / "records.jsonl")]
    assert runs.count("auto") == 2 and runs.count("random") == 1
    # other weights make another cell: with the shipped checkpoint the auto cell runs and passes
    shipped = [a for a in args if a not in ("--checkpoint", str(odd))]
    assert main(shipped) == 0


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--policies", "magic"], "policy 'magic' is not available"),
        (["--workers", "0"], "--workers"),
        (["--values", "1.5"], "penetration"),
        (["--density", "--values", "-3"], "density"),
        (["--warmup", "200", "--episode-length", "100"], "--warmup"),
        (["--at-penetration", "2"], "penetration"),
        (["--address", "auto"], "--address needs --backend ray"),
        (["--weather", "--values", "snow"], "--values"),
        (["--backend", "slurm"], "--backend"),
        (["--ring-length", "250"], "--ring-length=250.0: straight is not a ring"),
        (["--scenario", "ring", "--ring-length", "90"], "--ring-length=90.0"),
        (
            ["--checkpoint", "no/such.pt"],
            "--checkpoint=no/such.pt: checkpoint no/such.pt: file not found",
        ),
    ],
)
def test_bad_arguments_exit_with_a_clear_message(argv: list[str], message: str, capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        parse_args(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_default_penetration_sweep_cells() -> None:
    sweep = parse_args([])
    assert sweep == SweepConfig()
    assert sweep.results == Path("results/penetration")
    assert sweep.report_pdf == Path("results/penetration/penetration.pdf")
    density = parse_args(["--density", "--values", "60", "90", "--no-report"])
    assert density.axis_values() == (60.0, 90.0) and density.report_pdf is None
    assert density.results == Path("results/density")
    grid = cells(sweep)
    # 5 penetrations x 3 policies + the all-IDM 0 % reference, for 3 seeds
    assert len(grid) == 48
    assert {c.policy for c in grid} == {"auto", "acc-lc-tuned", "acc-lc", "idm"}
    assert {c.penetration for c in grid if c.policy == "idm"} == {0.0}


def test_a_ring_sweep_scales_the_ring_and_keeps_the_count_of_its_density() -> None:
    from mixed_traffic.experiments.sweep import cell_config

    sweep = parse_args(["--scenario", "ring", "--ring-length", "280", "--at-density",
                        str(22 / 0.28), "--values", str(1 / 22), "--no-report"])  # fmt: skip
    configs = [cell_config(c, sweep) for c in cells(sweep)]
    assert {c.ring_length for c in configs} == {(280.0,)}
    assert {round(c.density * 0.28) for c in configs} == {22}


def test_ray_backend_runs_cells_as_tasks(tmp_path: Path) -> None:
    pytest.importorskip("ray", reason="the ray extra is not installed")
    out = tmp_path / "res"
    assert main(["--penetration", "--values", "0.5", "--policies", "random", "--seeds", "0",
                 "--episode-length", "10", "--warmup", "1", "--no-report", "--no-traffic", "--backend", "ray",
                 "--workers", "2", "--out", str(out)]) == 0  # fmt: skip
    records = read_records(out / "records.jsonl")
    assert sorted((r["cell"]["policy"], r["status"]) for r in records) == [
        ("idm", "ok"),
        ("random", "ok"),
    ]


def test_detection_range_sweep_runs_each_range_and_reports_it(tmp_path: Path) -> None:
    """--detection-range cells carry the range, their env's sensors use it, and the report
    plots AvgR against it."""
    sweep = parse_args(["--detection-range", "--no-report"])
    assert sweep.axis_values() == (0.6, 0.8, 1.0, 1.2)
    from mixed_traffic.experiments.sweep import cell_config

    ranges = {cell_config(c, sweep).sensors.range_factor for c in cells(sweep)}
    assert ranges == {0.6, 0.8, 1.0, 1.2}
    out, pdf = tmp_path / "res", tmp_path / "dr.pdf"
    argv = ["--detection-range", "--values", "0.3", "1.0", "--policies", "acc-lc", "--seeds",
            "0", "--episode-length", "30", "--warmup", "5", "--at-density", "30", "--no-traffic",
            "--out", str(out), "--pdf", str(pdf)]  # fmt: skip
    assert main(argv) == 0
    records = read_records(out / "records.jsonl")
    assert sorted(r["cell"]["detection_range"] for r in records) == [0.3, 1.0]
    assert {r["config"]["sensors"]["range_factor"] for r in records} == {0.3, 1.0}
    assert (tmp_path / "dr-metrics_vs_detection_range.png").is_file()
    assert "detection range" in _pdf_text(pdf)
