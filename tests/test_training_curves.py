"""Training-curve figure (analysis.training_curves): legs laid end to end, one PNG."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from analysis.training_curves import PANELS, load_legs, main


def _leg(path: Path, steps: list[int]) -> Path:
    cols = {c: [0.1 * i for i in range(len(steps))] for c, _ in PANELS}
    pd.DataFrame({"env_steps": steps, **cols}).to_csv(path, index=False)
    return path


def test_legs_continue_the_transition_count(tmp_path: Path) -> None:
    a = _leg(tmp_path / "a.csv", [100, 200])
    b = _leg(tmp_path / "b.csv", [50, 150])
    df = load_legs([a, b])
    assert df["env_steps"].tolist() == [100, 200, 250, 350]
    assert df["leg"].tolist() == [1, 1, 2, 2]
    out = tmp_path / "curves.png"
    assert main([str(a), str(b), str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_file_that_is_not_curves_is_named(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y\n1,2\n")
    with pytest.raises(SystemExit):
        main([str(bad), str(tmp_path / "o.png")])
    assert "bad.csv" in capsys.readouterr().err


def test_a_fleet_search_curve_gets_its_panels(tmp_path: Path) -> None:
    from mixed_traffic.experiments.fleet import CURVE_FIELDS

    n = 12
    rows = {c: [0.01 * i for i in range(n)] for c in CURVE_FIELDS}
    rows.update(iteration=list(range(1, n + 1)), gain_scenario=["ring-260m"] * n)
    path = tmp_path / "curves.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    out = tmp_path / "fleet.png"
    assert main([str(path), str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
