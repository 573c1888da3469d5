"""Misuse gets a named error before any work starts: the env API out of order, wrong config
types, and CLI inputs that used to hang, trace back or lose a result."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from agents.training.config import TrainConfig
from mixed_traffic.config import EnvConfig, SensorConfig
from mixed_traffic.env.parallel import MixedTrafficEnv
from mixed_traffic.experiments import evaluate, sweep
from mixed_traffic.paths import REPO_ROOT

FOLLOW = {"decision": 1, "params": np.zeros((3, 2), np.float32)}


def test_env_misuse_is_named() -> None:
    env = MixedTrafficEnv(config=EnvConfig(density=60.0, episode_length=0.3))
    with pytest.raises(RuntimeError, match=r"before reset\(\)"):
        env.step({})
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"dict of actions.*got NoneType"):
        env.step(None)
    while env.agents:
        env.step(dict.fromkeys(env.agents, FOLLOW))
    assert math.isclose(env.sim_time, 0.3)
    with pytest.raises(RuntimeError, match=r"episode ended.*call reset\(\)"):
        env.step({})  # no silent steps past episode_length
    env.close()
    with pytest.raises(RuntimeError, match=r"after close\(\)"):
        env.step({})
    env.reset(seed=1)  # a closed env can start again
    assert env.agents
    env.close()


def test_wrong_nested_config_types_are_named() -> None:
    with pytest.raises(ValueError, match=r"EnvConfig.sensors=5 must be a SensorConfig"):
        EnvConfig(sensors=5)
    assert EnvConfig(sensors=SensorConfig(history=3)).sensors.history == 3


def test_a_training_budget_of_nan_minutes_is_refused() -> None:
    with pytest.raises(ValueError, match="minutes=nan"):
        TrainConfig(minutes=float("nan"), out=Path("x"))


def test_negative_sweep_seeds_are_refused(capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        sweep.parse_args(["--penetration", "--seeds", "-1"])
    assert stop.value.code == 2
    assert "--seeds=(-1,): seeds must be >= 0" in capsys.readouterr().err


def test_an_unwritable_records_file_fails_before_the_episode(tmp_path: Path, capsys) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(SystemExit) as stop:
        evaluate.main(["--policy", "idm", "--out", str(blocker / "records.jsonl")])
    assert stop.value.code == 2
    assert f"{blocker} is a file, not a folder" in capsys.readouterr().err


def test_a_sweep_writes_its_report_beside_its_results(tmp_path: Path) -> None:
    config = sweep.SweepConfig(out=tmp_path / "elsewhere")
    assert config.report_pdf == tmp_path / "elsewhere" / "penetration.pdf"
    assert sweep.SweepConfig().report_pdf == Path("results/penetration/penetration.pdf")
    reference = sweep.SweepConfig(update_reference=True).report_pdf
    assert reference == REPO_ROOT / "reports" / "penetration.pdf"


def test_a_step_too_coarse_for_the_av_control_is_warned_about() -> None:
    """At 1 s steps (SUMO's default) ACC-LC left the road 27 times in 90 s of urban."""
    with pytest.warns(UserWarning, match="step_length=1 s is longer than 0.5 s"):
        MixedTrafficEnv(scenario="straight", step_length=1.0).close()
