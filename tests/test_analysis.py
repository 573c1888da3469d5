"""analysis/: loading, statistics, tables, figures, findings and the PDF report, on synthetic records.

The analysis package is pure file processing, so these tests write records in the schema's layout
with realistic numbers (no SUMO needed). End-to-end tests on SUMO-produced records belong to the
sweep.
"""

from __future__ import annotations

import json
import math
import random
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from matplotlib.container import ErrorbarContainer

from analysis import benchmark_report, figures, findings, tables
from analysis.report import build_report
from analysis.results import (
    load_results,
    mean_ci,
    nonneg_mean_ci,
    records_to_frame,
    summarise,
    to_parquet,
)
from analysis.style import fmt_interval, fmt_mean_ci, fmt_num
from mixed_traffic.schema import CELL_KEYS, MACRO, METRICS

REPO = Path(__file__).resolve().parents[1]


def _metrics(policy: str, density: float, penetration: float, weather: str, rng: random.Random):
    """Plausible episode metrics: auto slightly better than acc-lc, DT-TF falling with penetration."""
    good = {"auto": 0.0, "acc-lc": 1.0, "idm": 1.5}.get(policy, 2.0)
    load = density / 120.0
    noise = lambda s: rng.gauss(0.0, s)  # noqa: E731
    av = penetration > 0
    return {
        "dt_tf": 70.0 - 12.0 * penetration * (1.0 - 0.4 * good) + 8.0 * (load - 1) + noise(0.8),
        "avg_dt_a": (53.6 + 3.5 * good) * load**0.3 + noise(0.6) if av else None,
        "avg_at_c": (5.5 + 1.5 * good) * load + noise(0.3) if av else None,
        "avg_di_c": (1.35 + 0.1 * good) * load**0.2 + noise(0.02) if av else None,
        "min_ttc_a": 3.15 - 0.2 * good + noise(0.1) if av else None,
        "avg_off_a": 0.17 + 0.02 * good + noise(0.01) if av else None,
        "avg_vel_a": 19.1 - 1.1 * good + noise(0.2) if av else None,
        "avg_jerk_a": 0.97 + 0.35 * good + noise(0.05) if av else None,
        "avg_dec_c": 0.44 + 0.11 * good + noise(0.02) if av else None,
        "pt_rt": (1.8 + 1.0 * good) * {"normal": 1, "rain": 3.5, "fog": 5.7, "night": 1.5}[weather]
        + abs(noise(0.2))
        if av
        else None,
        "avg_r": 0.4 - 0.1 * good + noise(0.02) if av else None,
        "avg_it": 2.1 + noise(0.1) if av else None,
        "speed_std": 2.5 - 1.5 * penetration * (1.0 - 0.4 * good) + noise(0.1),
        "fuel": 7.0 - 0.8 * penetration * (1.0 - 0.4 * good) + noise(0.1),
        "speed_std_ahead": 1.2 - 0.5 * penetration + noise(0.05) if av else None,
        "speed_std_behind": 1.2 - 0.5 * penetration - 0.3 * (1.0 - 0.5 * good) + noise(0.05)
        if av
        else None,
        "measured_density": density + noise(2.0),
        "mean_speed": 16.0 - 2 * (load - 1) + noise(0.3),
        "vehicles_crossed": 150 + rng.randint(-5, 5),
        "av_trips": int(150 * penetration) if av else 0,
        "route_completion": 100.0 if av else None,
        "collisions": 1 if (policy == "acc-lc" and penetration == 1.0) else 0,
        "teleports": 0,
        "terminal_collision": 0,
        "terminal_off_road": 0,
        "terminal_route_deviation": 0,
        "terminal_red_light": 0,
        "terminal_speed_limit": 0,
    }


def _record(policy, scenario, density, penetration, weather, seed, rng, status="ok", error=None):
    cell = {
        "policy": policy,
        "scenario": scenario,
        "density": density,
        "penetration": penetration,
        "weather": weather,
        "seed": seed,
    }
    config = {
        "scenario": scenario,
        "density": density,
        "penetration": penetration,
        "weather": weather,
        "seed": seed,
        "episode_length": 120.0,
        "step_length": 0.1,
    }
    return {
        "cell": cell,
        "status": status,
        "error": error,
        "config": config,
        "seed": seed,
        "sumo_version": "1.28.0",
        "git_revision": "abc1234",
        "code": "0b0b39a57b8a",
        "created": f"2025-01-01T00:{rng.randint(0, 59):02d}:{rng.randint(0, 59):02d}+00:00",
        "wall_time": 30.0 + rng.random(),
        "metrics": (_metrics(policy, density, penetration, weather, rng) if status == "ok" else {}),
    }


def write_results(
    path: Path,
    policies=("auto", "acc-lc"),
    penetrations=(0.2, 0.6, 1.0),
    densities=(120.0,),
    weathers=("normal",),
    seeds=(0, 1, 2),
    reference=True,
    failed=True,
    truncated=True,
) -> list[dict]:
    """Write a synthetic ``records.jsonl``; returns the complete (parsed) records written."""
    rng = random.Random(0)
    records = []
    for policy in policies:
        for density in densities:
            for pen in penetrations:
                for weather in weathers:
                    for seed in seeds:
                        records.append(
                            _record(policy, "straight", density, pen, weather, seed, rng)
                        )
    if reference:
        for density in densities:
            for seed in seeds:
                records.append(_record("idm", "straight", density, 0.0, "normal", seed, rng))
    if failed:
        records.append(
            _record(
                "auto", "straight", 180.0, 0.6, "normal", 0, rng, "failed",
                "FatalTraCIError: connection closed by SUMO",
            )
        )  # fmt: skip
    path.mkdir(parents=True, exist_ok=True)
    with open(path / "records.jsonl", "w") as f:
        for r in records:
            f.write(json.dumps(r) + "\n")
        if truncated:
            f.write(json.dumps(records[0])[:57])  # an interrupted append
    return records


@pytest.fixture()
def results(tmp_path: Path) -> tuple[Path, list[dict]]:
    d = tmp_path / "results"
    return d, write_results(d)


# ---------------------------------------------------------------- loading and statistics


def test_load_results_shape(results):
    d, records = results
    with pytest.warns(UserWarning, match="truncated last line"):
        df = load_results(d)
    assert len(df) == len(records) == 2 * 3 * 3 + 3 + 1
    for col in (*CELL_KEYS, "status", "error", "seed", "sumo_version", "git_revision", "code",
                "wall_time"):  # fmt: skip
        assert col in df.columns
    for key in METRICS:
        assert key in df.columns
    failed = df[df["status"] == "failed"]
    assert len(failed) == 1 and "FatalTraCIError" in failed["error"].iloc[0]
    assert df.loc[df["status"] == "ok", "dt_tf"].notna().all()
    assert df["episode_length"].eq(120.0).all()
    first = records[0]
    row = df[(df["policy"] == "auto") & (df["penetration"] == 0.2) & (df["seed"] == 0)].iloc[0]
    assert row["avg_dt_a"] == pytest.approx(first["metrics"]["avg_dt_a"])


def test_parquet_roundtrip_and_no_duplicates(results):
    d, _records = results
    with pytest.warns(UserWarning):
        df = load_results(d)
    to_parquet(df, d / "records.parquet")
    with pytest.warns(UserWarning):
        both = load_results(d)  # the same records from jsonl and parquet appear once
    assert len(both) == len(df)
    only = load_results(d / "records.parquet")
    assert len(only) == len(df)
    pd.testing.assert_series_equal(
        only["dt_tf"].reset_index(drop=True), df["dt_tf"].reset_index(drop=True)
    )


def test_failed_then_successful_rerun_keeps_success(tmp_path):
    rng = random.Random(1)
    failed = _record("auto", "straight", 120.0, 0.2, "normal", 0, rng, "failed", "boom")
    ok = _record("auto", "straight", 120.0, 0.2, "normal", 0, rng)
    failed["created"], ok["created"] = "2025-01-01T00:00:00", "2025-01-01T01:00:00"
    (tmp_path / "records.jsonl").write_text(json.dumps(failed) + "\n" + json.dumps(ok) + "\n")
    df = load_results(tmp_path)
    assert list(df["status"]) == ["ok"]


def test_a_record_without_status_or_code_is_not_counted_ok(tmp_path):
    """Issue 25 D8: such a record has no provenance; the report lists it as invalid."""
    rng = random.Random(2)
    ok = _record("auto", "straight", 120.0, 0.2, "normal", 0, rng)
    no_code = {k: v for k, v in _record("auto", "straight", 120.0, 0.4, "normal", 0, rng).items()
               if k != "code"}  # fmt: skip
    no_status = {k: v for k, v in _record("idm", "straight", 120.0, 0.0, "normal", 0, rng).items()
                 if k != "status"}  # fmt: skip
    lines = [json.dumps(r) for r in (ok, no_code, no_status)]
    (tmp_path / "records.jsonl").write_text("\n".join(lines) + "\n")
    df = load_results(tmp_path)
    assert sorted(df["status"]) == ["invalid", "invalid", "ok"]
    assert df.loc[df["status"] == "ok", "penetration"].tolist() == [0.2]


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_results(tmp_path / "nope")
    with pytest.raises(FileNotFoundError, match=r"no records\.jsonl"):
        load_results(tmp_path)


def test_ci_hand_computed():
    # values 1, 2, 3, 4: mean 2.5, s = sqrt(5/3), t_{0.975,3} = 3.1824 -> half = 3.1824*s/2
    mean, half, n = mean_ci([1.0, 2.0, 3.0, 4.0, float("nan"), None])
    assert (mean, n) == (2.5, 4)
    assert half == pytest.approx(3.1824 * math.sqrt(5 / 3) / 2, rel=1e-4)
    assert half == pytest.approx(2.0541, abs=1e-3)
    m1, h1, n1 = mean_ci([7.0])
    assert (m1, n1) == (7.0, 1) and math.isnan(h1)


def test_summarise_groups(results):
    d, _ = results
    with pytest.warns(UserWarning):
        df = load_results(d)
    s = summarise(df, ["policy", "penetration"], ["dt_tf"])
    row = s[(s["policy"] == "auto") & (s["penetration"] == 0.2)].iloc[0]
    vals = df[(df["policy"] == "auto") & (df["penetration"] == 0.2)]["dt_tf"]
    assert row["n_ok"] == 3 and row["dt_tf_n"] == 3
    assert row["dt_tf_mean"] == pytest.approx(vals.mean())
    # DT-TF is a time (>= 0): the log-scale interval mean * exp(-+t s / (sqrt(n) mean))
    rel = 4.3027 * vals.std(ddof=1) / (math.sqrt(3) * vals.mean())
    assert row["dt_tf_lo"] == pytest.approx(vals.mean() * math.exp(-rel), rel=1e-4)
    assert row["dt_tf_hi"] == pytest.approx(vals.mean() * math.exp(rel), rel=1e-4)
    fail = s[(s["policy"] == "auto") & (s["penetration"] == 0.6)].iloc[0]
    assert fail["n_failed"] == 1 and fail["n_ok"] == 3


SPREAD = [0.3, 2.5, 5.0]  # speed std over 3 seeds whose t-interval reaches below 0 m/s


def _spread_frame() -> pd.DataFrame:
    """auto at 20 % (speed std ``SPREAD``) and 100 %, all human at 0 % with a wide spread too;
    wave speed (signed) beside: one row per seed."""
    cells = [("auto", 0.2, SPREAD), ("auto", 1.0, [0.4, 0.5, 0.6]), ("idm", 0.0, [0.2, 3.0, 4.0])]
    records = [
        {"cell": {"policy": policy, "scenario": "straight", "density": 120.0, "penetration": pen,
                  "weather": "normal", "seed": seed},
         "status": "ok", "code": "c0de",
         "metrics": {"speed_std": v, "wave_speed": (-10.0, 1.0, 12.0)[seed]}}
        for policy, pen, values in cells for seed, v in enumerate(values)
    ]  # fmt: skip
    return records_to_frame(records)


def test_summarise_intervals_of_nonnegative_metrics_stay_above_zero():
    s = summarise(_spread_frame(), ["policy", "penetration"], ["speed_std", "wave_speed"])
    row = s[(s["policy"] == "auto") & (s["penetration"] == 0.2)].iloc[0]
    assert 0 < row["speed_std_lo"] < row["speed_std_mean"] < row["speed_std_hi"]
    assert (s["speed_std_lo"] >= 0).all()
    mean, half, _ = mean_ci([-10.0, 1.0, 12.0])  # signed: the symmetric t-interval, below 0
    assert row["wave_speed_lo"] == pytest.approx(mean - half) and row["wave_speed_lo"] < 0
    assert row["wave_speed_hi"] == pytest.approx(mean + half)


def test_error_bars_of_nonnegative_metrics_stay_above_zero():
    df = _spread_frame()
    _, (ax, bars) = figures.new_figure(6, 3, ncols=2)
    assert figures._penetration_panel(ax, df, "speed_std")
    figures._bars(bars, summarise(df, ["policy"], ["speed_std"]), "speed_std")
    lows = [
        seg[:, 1].min()
        for a in (ax, bars)
        for c in a.containers
        if isinstance(c, ErrorbarContainer)
        for lines in c.lines[2]
        for seg in lines.get_segments()
    ]
    assert len(lows) == 2 + 1 + 2 and min(lows) > 0  # 2 line points, the 0 % point, 2 bars
    assert min(lows) < 0.3  # asymmetric: the whisker still reaches down towards 0
    band = [p for p in ax.patches if p.get_alpha() == 0.10]  # the 0 % reference band
    assert len(band) == 1 and band[0].get_y() > 0


def test_tables_print_the_asymmetric_interval():
    df = _spread_frame()
    shown = tables.format_table(tables.metric_table(df, ["speed_std", "wave_speed"],
                                                    by=["policy", "penetration"]))  # fmt: skip
    _, lo, hi, _ = nonneg_mean_ci(SPREAD)
    cell = shown[(shown["policy"] == "auto") & (shown["AV share"] == "20 %")].iloc[0]
    assert cell["speed std (m/s)"] == f"2.60 [{lo:.2f}, {hi:.2f}]" == "2.60 [0.27, 24.59]"
    mean, half, _ = mean_ci([-10.0, 1.0, 12.0])
    assert cell["wave speed (km/h)"] == f"{mean:.2f} ± {half:.2f}"  # signed: symmetric
    assert fmt_interval(2.47, 2.01, 3.031) == "2.47 [2.01, 3.03]"
    assert fmt_interval(2.47, math.nan, math.nan) == "2.47" and fmt_interval(None, 1, 2) == "n/a"


def test_benchmark_table_prints_the_ratio_interval():
    row = {"task": "ring-v2", "policy": "idm", "score": -0.08, "score_half_width": 0.04,
           "mean_speed": 2.2, "speed_std": 0.5, "fuel": 41.0, "dt_tf": math.nan,
           "std_ratio": 0.22, "std_ratio_lo": 0.05, "std_ratio_hi": 0.97,
           "terminal_events": 0}  # fmt: skip
    head, body = benchmark_report.table_rows([row])
    assert body[2] == "-0.08 ± 0.04" and body[head.index("speed std / all human [95 % CI]")] == (
        "0.22 [0.05, 0.97]"
    )


# ---------------------------------------------------------------- tables, figures, findings


def test_tables(results):
    d, _ = results
    with pytest.warns(UserWarning):
        df = load_results(d)
    macro = tables.macro_table(df)
    assert list(macro["policy"]) == ["auto", "acc-lc"]
    assert macro.attrs["condition"]["penetration"] == pytest.approx(0.2)
    for m in MACRO:
        assert f"{m}_mean" in macro.columns
    for col in tables.SAFETY_COLUMNS:
        assert col in macro.columns
    text = tables.to_text(tables.micro_table(df), "markdown")
    assert "MinTTC-A (s)" in text and "collisions" in text and " [" in text
    cells = tables.cell_table(df)
    assert len(cells) == 2 * 3 + 1 + 1  # + the 0 % reference + the failed-only cell
    assert "AV share" in tables.to_text(cells, "text")
    safety = tables.safety_table(df)
    assert int(safety["failed"].sum()) == 1


def test_figures(tmp_path):
    d = tmp_path / "results"
    write_results(d, densities=(60.0, 120.0, 180.0), weathers=("normal", "rain"), truncated=False)
    df = load_results(d)
    out = tmp_path / "figs"
    paths = [
        figures.plot_penetration(df, out),
        figures.plot_density(df, out),
        figures.plot_micro(df, out),
        figures.plot_weather(df, out),
    ]
    for p in paths:
        assert p is not None and p.suffix == ".png" and p.stat().st_size > 10_000


def test_smoothing_table_figure_and_findings(results, tmp_path):
    d, _ = results
    with pytest.warns(UserWarning):
        df = load_results(d)
    table = tables.smoothing_table(df)
    # as in the per-cell table: 2 policies x 3 shares, the 0 % reference and the failed cell
    assert len(table) == 2 * 3 + 1 + 1
    text = tables.to_text(table, "text")
    for head in ("DT-TF (s)", "speed std (m/s)", "fuel (l/100 km)", "speed std ahead (m/s)",
                 "speed std behind (m/s)"):  # fmt: skip
        assert head in text, head
    assert "collisions" not in text  # the safety counts stay in the per-cell table
    path = figures.plot_smoothing(df, tmp_path)
    assert path is not None and path.stat().st_size > 10_000
    found = "\n".join(findings.findings(df))
    assert "fuel with auto falls from" in found
    assert "Speed std behind vs ahead of the AVs with auto at 20 %" in found
    assert "calmer behind; paired t-test over 3 seeds" in found


def test_records_without_the_smoothing_measures_still_load_and_report(tmp_path):
    """Records written before fuel and speed_std_ahead/behind existed: NaN columns, no
    smoothing table or figure, and the report still builds."""
    d = tmp_path / "old"
    records = write_results(d, failed=False, truncated=False)
    new = ("speed_std", "fuel", "speed_std_ahead", "speed_std_behind")
    with open(d / "records.jsonl", "w") as f:
        for r in records:
            r["metrics"] = {k: v for k, v in r["metrics"].items() if k not in new}
            f.write(json.dumps(r) + "\n")
    df = load_results(d)
    assert df[list(new)].isna().all().all() and df["dt_tf"].notna().all()
    assert tables.smoothing_table(df).empty
    assert figures.plot_smoothing(df, tmp_path) is None
    assert "smoothing" not in figures.all_figures(df, tmp_path / "figs")
    assert build_report(d, tmp_path / "old.pdf").stat().st_size > 20_000


def test_figures_skip_missing_dimensions(results, tmp_path):
    d, _ = results
    with pytest.warns(UserWarning):
        df = load_results(d)
    assert figures.plot_density(df, tmp_path) is None  # one density only
    assert figures.plot_weather(df, tmp_path) is None  # one weather only
    assert figures.plot_penetration(df[df["penetration"] == 0.2], tmp_path) is None


def test_findings_wording(results):
    d, _ = results
    with pytest.warns(UserWarning):
        df = load_results(d)
    text = "\n".join(findings.findings(df))
    assert "DT-TF with auto falls from" in text
    assert "paired t-test over 3 seeds: difference" in text  # same seeds at every cell
    assert "collisions" in text and "AV trips" in text
    assert "1 of 22 episodes failed" in text
    # identical data for two policies -> no difference can be claimed
    same = df[df["policy"] == "auto"].copy()
    same2 = same.copy()
    same2["policy"] = "acc-lc"
    text2 = " ".join(findings.findings(pd.concat([same, same2], ignore_index=True)))
    assert "within noise; paired t-test over 3 seeds: difference 0.00 ± 0.00" in text2


# ---------------------------------------------------------------- report


def test_report_pdf_contains_labels_and_numbers(results, tmp_path):
    pypdf = pytest.importorskip("pypdf")
    d, _ = results
    out = tmp_path / "reports" / "synthetic.pdf"
    with pytest.warns(UserWarning):
        path = build_report(d, out, title="Synthetic sweep")
    assert path == out and out.stat().st_size > 20_000
    assert not list(out.parent.glob("*.tmp"))
    text = "\n".join(p.extract_text() for p in pypdf.PdfReader(out).pages)
    for name in (
        "Synthetic sweep",
        "DT-TF",
        "AvgDT-A",
        "AvgAT-C",
        "AvgDI-C",
        "MinTTC-A",
        "AvgDEC-C",
        "Traffic smoothing per cell",
        "fuel (l/100 km)",
        "speed std behind (m/s)",
    ):
        assert name in text, name
    for prov in ("abc1234", "0b0b39a57b8a", "1.28.0", "FatalTraCIError"):
        assert prov in text, prov
    assert "Welch's t-test" in " ".join(text.split())  # the wording rule is stated
    assert "log-scale (delta-method) t-interval" in " ".join(text.split())  # and the intervals'
    with pytest.warns(UserWarning):
        df = load_results(d)
    sel = df[(df["policy"] == "auto") & (df["penetration"] == 0.2)]
    mean, half, _ = mean_ci(sel["avg_dt_a"])
    assert fmt_mean_ci(mean, half).split(" ± ")[0] in text
    assert fmt_num(mean) in text
    dt = df[(df["policy"] == "acc-lc") & (df["penetration"] == 1.0)]["dt_tf"].mean()
    assert fmt_num(dt) in text


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mixed_traffic.report", *args],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=240,
    )


def test_report_cli(results, tmp_path):
    d, _ = results
    out = tmp_path / "cli.pdf"
    proc = _cli(str(d), "--out", str(out), "--title", "CLI report")
    assert proc.returncode == 0, proc.stderr
    assert out.exists() and str(out) in proc.stdout
    assert _cli(str(d)).returncode == 0  # by default beside the results, never in reports/
    assert (d / f"{d.name}.pdf").is_file()


def test_report_cli_errors(tmp_path):
    proc = _cli(str(tmp_path / "missing"))
    assert proc.returncode == 2 and "does not exist" in proc.stderr
    (tmp_path / "empty").mkdir()
    proc = _cli(str(tmp_path / "empty"))
    assert proc.returncode == 2 and "records" in proc.stderr
    (tmp_path / "blank").mkdir()
    (tmp_path / "blank" / "records.jsonl").write_text("")
    proc = _cli(str(tmp_path / "blank"))
    assert proc.returncode == 2 and "no records" in proc.stderr
    assert _cli("--help").returncode == 0


def test_analysis_imports_without_sumo_or_torch():
    code = (
        "import sys, analysis.report, analysis.figures, mixed_traffic.report\n"
        "bad = [m for m in ('libsumo', 'traci', 'torch', 'sumolib') if m in sys.modules]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO, timeout=120)
