"""Policy specs (acc-lc:T=1.0,...), acc-lc-tuned and how the tuning chooses."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from agents.policies import make_policy
from agents.rules.spec import parse_policy
from agents.rules.tuned import TUNED_FILE, tuned_params
from mixed_traffic.config import EnvConfig
from mixed_traffic.experiments.evaluate import main as evaluate
from mixed_traffic.experiments.runner import run_episode, sumo_drives
from mixed_traffic.experiments.sweep import SweepConfig
from mixed_traffic.experiments.tune_acc_lc import default_choice, ranked, setting_table


def test_specs_are_canonical_and_reach_the_rule() -> None:
    assert str(parse_policy("acc-lc:speed_factor=1,T=1")) == "acc-lc:T=1.0,speed_factor=1.0"
    assert str(parse_policy(" acc-lc ")) == "acc-lc"
    policy = make_policy("acc-lc:T=1.1,a=2.0,iidm=false", dt=0.2)
    assert (policy.c.T, policy.c.a, policy.c.iidm, policy.c.dt) == (1.1, 2.0, False, 0.2)
    assert policy.name == "acc-lc:a=2.0,T=1.1,iidm=false"
    assert policy.params == {"a": 2.0, "T": 1.1, "iidm": False}
    stern = make_policy("follower-stopper:dx0=4/5/6,window=20")
    assert stern.c.dx0 == (4.0, 5.0, 6.0) and stern.c.window == 20.0
    # the conservative variant keeps its own base under the changed field
    assert make_policy("acc-lc-conservative:T=1.0").c.s0 == 3.0
    # whether SUMO drives the AVs is read from the parsed spec, not the raw text
    assert sumo_drives(" idm ") and not sumo_drives("acc-lc:T=1.0")


@pytest.mark.parametrize(
    ("spec", "needle"),
    [
        ("acc-lc:Tx=1", "'Tx' is not a field of AccLcConfig"),
        ("acc-lc:T=-1", "AccLcConfig.T=-1.0 must be finite and > 0"),
        ("acc-lc:T=abc", "T='abc' must be a number"),
        ("acc-lc:T=inf", "T='inf' must be finite"),
        ("acc-lc:speed_factor=2", "speed_factor=2.0 must be <= 1.5"),
        ("acc-lc:dt=0.2", "'dt' is set by the env"),
        ("acc-lc:iidm=maybe", "iidm='maybe' must be true or false"),
        ("acc-lc:T", "must read field=value"),
        ("auto:T=1", "'auto' takes no parameters"),
        ("acc-lcx", "'acc-lcx' is not available"),
        (
            "follower-stopper:decel=0/1/1",
            "SternConfig.decel=(0.0, 1.0, 1.0) must be finite and > 0",
        ),
    ],
)
def test_bad_specs_get_one_line_errors(spec: str, needle: str) -> None:
    with pytest.raises(ValueError) as e:
        parse_policy(spec)
    assert needle in str(e.value) and "\n" not in str(e.value)


def test_cli_refuses_a_bad_field_before_any_episode(capsys, tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as e:
        evaluate(["--policy", "acc-lc:Tx=1.0", "--out", str(tmp_path / "r.jsonl")])
    assert e.value.code == 2
    assert "'Tx' is not a field of AccLcConfig" in capsys.readouterr().err
    assert not (tmp_path / "r.jsonl").exists()
    with pytest.raises(ValueError, match="T='x' must be a number"):
        SweepConfig(policies=("acc-lc:T=x",))
    assert SweepConfig(policies=("acc-lc:T=1", "acc-lc:T=1.0")).policies == ("acc-lc:T=1.0",)


def test_a_spec_runs_and_its_record_carries_the_resolved_parameters() -> None:
    cfg = EnvConfig(scenario="straight", density=60, penetration=0.2, episode_length=20)
    rec = run_episode(cfg, "acc-lc:speed_factor=1,T=1.0", warmup=5)
    assert rec["status"] == "ok" and rec["cell"]["policy"] == "acc-lc:T=1.0,speed_factor=1.0"
    assert rec["policy_params"] == {"T": 1.0, "speed_factor": 1.0}


@pytest.mark.skipif(not TUNED_FILE.is_file(), reason="no tuned file shipped yet")
def test_acc_lc_tuned_resolves_per_family_and_falls_back_to_the_default() -> None:
    data = json.loads(TUNED_FILE.read_text())
    family = next(iter(data["families"]))
    policy = make_policy("acc-lc-tuned", family=family)
    want = data["families"][family]["params"]
    assert {k: getattr(policy.c, k) for k in want} == want
    assert policy.params["tuned_for"] == family
    assert tuned_params("no-such-family")["tuned_for"] == "default"
    # a spec's own field wins over the tuned one
    assert make_policy("acc-lc-tuned:T=1.3", family=family).c.T == 1.3


def _record(policy: str, p: float, speed: float, events: int = 0, ok: bool = True) -> dict:
    metrics = {"mean_speed": speed, "terminal_collision": events, "collisions": 0}
    return {"cell": {"policy": policy, "penetration": p}, "status": "ok" if ok else "failed",
            "metrics": metrics if ok else {}}  # fmt: skip


def test_the_choice_is_the_fastest_setting_without_a_terminal_event() -> None:
    records = [
        _record("fast", 0.5, 20.0, events=1), _record("fast", 0.5, 20.0),
        _record("good", 0.5, 18.0), _record("good", 0.5, 17.0),
        _record("slow", 0.5, 10.0), _record("slow", 0.5, 11.0),
        _record("broken", 0.5, 19.0), _record("broken", 0.5, 0.0, ok=False),
        _record("good", 1.0, 30.0),  # another penetration: not part of this table
    ]  # fmt: skip
    table = setting_table(records, 0.5)
    assert table["good"]["mean_speed"] == pytest.approx(17.5)
    assert ranked(table, seeds=2) == ["good", "slow"]
    # the default: admissible in every family, best mean share of each family's best
    fam = {
        "x": {"table": table},
        "y": {"table": {**table, "slow": {**table["slow"], "mean_speed": 40.0}}},
    }
    assert default_choice(_as_specs(fam), seeds=2)["params"] == {
        "T": 1.4,
        "speed_factor": 0.95,
        "a": 1.5,
    }


def _as_specs(families: dict) -> dict:
    """The test's setting names as real specs (the default decodes their parameters)."""
    names = {
        "good": "acc-lc:T=1.0,speed_factor=1.0,a=2.0",
        "slow": "acc-lc:T=1.4,speed_factor=0.95,a=1.5",
    }
    out = {}
    for fam, entry in families.items():
        out[fam] = {"table": {str(parse_policy(names.get(k, f"acc-lc:T={1 + i}"))): v
                              for i, (k, v) in enumerate(entry["table"].items())}}  # fmt: skip
    return out
