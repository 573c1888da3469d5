"""Issue 25's collection of bad inputs in one place (over 100), one table per area: each fails
with a one-line error that names what is wrong, before any work starts.

- CLIs (sweep, evaluate, train, compare, fleet, bench) run in this process through their
  ``main(argv)``: exit status 2, no traceback, exactly one ``prog: error: ...`` line and nothing
  after it, the expected words in it. Every function that would start work (episodes, training,
  the fleet search, benchmark sections) is replaced by one that fails the test, and the
  ``--out`` folder holds no file afterwards; where a records file was there before, it is
  byte-identical afterwards (nothing already written is lost). Three cases run as real
  processes, to show that no traceback reaches the terminal there either.
- The env API and the config dataclasses raise a named exception whose message is one line; a
  refused step leaves the simulation where it was.
- Scenario files and checkpoints are refused by their loaders with one line naming the file.

``TALLY`` counts the cases per area (docs/reliability.md shows it).
"""

from __future__ import annotations

import gzip
import math
import pickle
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from agents.policies import SHIPPED_CHECKPOINT, make_policy
from mixed_traffic.config import EnvConfig, HumanConfig, SensorConfig
from mixed_traffic.env.parallel import MixedTrafficEnv, parallel_env
from mixed_traffic.experiments import bench, compare, evaluate, fleet, study, sweep, train
from mixed_traffic.world.backend import binary
from mixed_traffic.world.registry import load_scenario

REPO = Path(__file__).resolve().parents[2]
PROG = {
    "sweep": "python -m mixed_traffic.sweep",
    "evaluate": "python -m mixed_traffic.evaluate",
    "train": "python -m mixed_traffic.train",
    "compare": "python -m mixed_traffic.compare",
    "fleet": "python -m mixed_traffic.experiments.fleet",
    "bench": "python -m mixed_traffic.bench",
    "study": "python -m mixed_traffic.study",
}
MODULE = {"sweep": sweep, "evaluate": evaluate, "train": train, "compare": compare,
          "fleet": fleet, "bench": bench, "study": study}  # fmt: skip
#: Where each CLI writes, unless the case names its own --out ({out}: an empty folder per case).
OUT = {"sweep": "--out {out}", "evaluate": "--out {out}/records.jsonl", "train": "--out {out}",
       "compare": "--out {out}", "fleet": "--out {out}", "bench": "",
       "study": "--out {out}"}  # fmt: skip
CKPT = str(SHIPPED_CHECKPOINT)
RECORD = b'{"status": "ok", "code": "earlier", "metrics": {}}\n'


def cli(name: str, argv: str, needle: str, case_id: str, *, keep: bool = False) -> Any:
    """A CLI case: ``argv`` (split on spaces; {d} = the bad files' folder, {out} = this case's
    output folder, {ckpt} = the shipped checkpoint) must exit 2 with ``needle`` in its error
    line. ``keep``: a records file is in {out} beforehand and must stay byte-identical."""
    args = argv.split() + ([] if "--out" in argv else OUT[name].split())
    return pytest.param(name, args, needle, keep, id=f"{name}-{case_id}")


# --------------------------------------------------------------------------- CLI tables
# fmt: off
SWEEP = [
    cli("sweep", "--scenario nowhere", "--scenario='nowhere': unknown scenario", "unknown-scenario"),
    cli("sweep", "--scenario {d}/torn.net.xml", "torn.net.xml is malformed XML", "corrupt-net"),
    cli("sweep", "--seeds -1", "--seeds=(-1,): seeds must be >= 0", "negative-seed", keep=True),
    cli("sweep", "--seeds", "argument --seeds: expected at least one", "no-seed"),
    cli("sweep", "--density --values nan", "EnvConfig.density=nan", "nan-density"),
    cli("sweep", "--density --values -5", "EnvConfig.density=-5.0", "negative-density"),
    cli("sweep", "--density --values inf", "EnvConfig.density=inf", "inf-density"),
    cli("sweep", "--values 1.5", "EnvConfig.penetration=1.5", "penetration-above-1"),
    cli("sweep", "--values -0.1", "EnvConfig.penetration=-0.1", "penetration-below-0"),
    cli("sweep", "--policies magic", "policy 'magic' is not available", "unknown-policy"),
    cli("sweep", "--checkpoint {d}/garbage.pt", "garbage.pt: corrupt or unreadable", "bad-checkpoint"),
    cli("sweep", "--policies acc-lc --checkpoint {ckpt}", "policy in --policies would use it", "unused-checkpoint"),
    cli("sweep", "--workers 0", "--workers=0: must be >= 1", "zero-workers"),
    cli("sweep", "--detection-range --values 3", "SensorConfig.range_factor=3.0", "range-above-2"),
    cli("sweep", "--detection-range --values 0", "SensorConfig.range_factor=0.0", "zero-range"),
    cli("sweep", "--weather --values snow", "EnvConfig.weather='snow' is not one of", "unknown-weather"),
    cli("sweep", "--episode-length nan", "--episode-length=nan: must be in", "nan-episode", keep=True),
    cli("sweep", "--out {d}/blocker/results", "blocker is a file, not a folder", "unwritable-out"),
    cli("sweep", "--pdf {d}/blocker/r.pdf", "cannot write report to", "unwritable-pdf"),
]
# fmt: on
# fmt: off
EVALUATE = [
    cli("evaluate", "--out {d}/blocker/r.jsonl", "blocker is a file, not a folder", "unwritable-out"),
    cli("evaluate", "--out {d}", "is a folder, not a records file", "out-is-a-folder"),
    cli("evaluate", "--scenario {d}/missing.net.xml", "missing.net.xml does not exist", "missing-net"),
    cli("evaluate", "--scenario {d}/road.txt", "unknown scenario", "not-a-net-file"),
    cli("evaluate", "--scenario {d}/torn.net.xml", "torn.net.xml is malformed XML", "corrupt-net"),
    cli("evaluate", "--scenario {d}/nocars.net.xml", "no lane that passenger cars may use", "no-car-lanes"),
    cli("evaluate", "--penetration 1.5", "EnvConfig.penetration=1.5", "penetration-above-1", keep=True),
    cli("evaluate", "--density nan", "EnvConfig.density=nan", "nan-density"),
    cli("evaluate", "--seeds -1", "EnvConfig.seed=-1", "negative-seed"),
    cli("evaluate", "--episode-length 0", "EnvConfig.episode_length=0.0", "zero-episode"),
    cli("evaluate", "--episode-length 0.05", "shorter than one step", "episode-under-a-step"),
    cli("evaluate", "--warmup 500", "warmup=500.0 s must be in", "warmup-past-the-end"),
    cli("evaluate", "--policy nope", "argument --policy: policy 'nope' is not available", "unknown-policy"),
    cli("evaluate", "--policy auto --checkpoint {d}/garbage.pt", "garbage.pt: corrupt or unreadable",
        "bad-checkpoint", keep=True),
    cli("evaluate", "--checkpoint {ckpt}", "--checkpoint is used by a learned policy", "unused-checkpoint"),
    cli("evaluate", "--copies 0", "EnvConfig.copies=0 is out of range", "zero-copies"),
    cli("evaluate", "--scenario urban --copies 2", "copies=2: 'urban' is the urban family", "urban-copies"),
    cli("evaluate", "--copies 1024 --density 400", "more than the", "copies-beyond-memory"),
    cli("sweep", "--copies 0", "--copies=0: EnvConfig.copies=0 is out of range", "sweep-zero-copies"),
    cli("evaluate", "--policy transfuser --checkpoint {d}/garbage.pt", "garbage.pt: corrupt or unreadable",
        "bad-study-checkpoint"),
    cli("evaluate", "--gif {d}/blocker/e.gif", "cannot write GIF to", "unwritable-gif"),
]
# fmt: on
# fmt: off
TRAIN = [
    cli("train", "--minutes nan", "TrainConfig.minutes=nan", "nan-minutes"),
    cli("train", "--minutes -1", "TrainConfig.minutes=-1.0", "negative-minutes"),
    cli("train", "--minutes inf", "TrainConfig.minutes=inf", "inf-minutes"),
    cli("train", "--workers 2", "give a budget", "no-budget"),
    cli("train", "--env-steps 10 --batch-size 0", "TrainConfig.batch_size=0", "zero-batch"),
    cli("train", "--env-steps 10 --lr nan", "TrainConfig.lr=nan", "nan-lr"),
    cli("train", "--env-steps 10 --horizon 0.4", "TrainConfig.horizon=0.4", "gamma-below-0"),
    cli("train", "--env-steps 10 --scenarios nowhere", "unknown scenario 'nowhere'", "unknown-scenario"),
    cli("train", "--env-steps 10 --scenarios straight-eval", "held-out", "eval-scenario"),
    cli("train", "--env-steps 10 --fleet-iterations -1", "TrainConfig.fleet_iterations=-1",
        "negative-fleet-iterations"),
    cli("train", "--env-steps 10 --seed -1", "TrainConfig.seed=-1", "negative-seed"),
    cli("train", "--env-steps 10 --update-ratio nan", "TrainConfig.update_ratio=nan", "nan-update-ratio"),
    cli("train", "--env-steps 10 --learner-threads 0", "TrainConfig.learner_threads=0", "zero-threads"),
    cli("train", "--env-steps 10 --init {d}/garbage.pt", "garbage.pt: corrupt or unreadable", "bad-init"),
    cli("train", "--env-steps 10 --out {d}/blocker", "--out: cannot use", "out-is-a-file"),
    cli("train", "--env-steps 10 --baseline nope", "TrainConfig.baseline='nope'", "unknown-baseline"),
    cli("train", "--env-steps 10 --baseline transfuser", "needs --no-residual", "baseline-form"),
    cli("train", "--env-steps 10 --baseline head --ablation nohis", "its own method",
        "baseline-and-ablation"),
]
# fmt: on
# fmt: off
STUDY = [
    cli("study", "--seeds 0", "give at least 2 distinct seeds", "one-seed"),
    cli("study", "--seeds 1 1", "give at least 2 distinct seeds", "repeated-seed"),
    cli("study", "--env-steps 0", "the training budget must be > 0", "zero-budget"),
    cli("study", "--scenario nowhere", "unknown scenario", "unknown-scenario"),
    cli("study", "--policies magic", "policy 'magic' is not available", "unknown-policy"),
    cli("study", "--ablations --reference head", "--reference='head': not among", "bad-reference"),
    cli("study", "--no-train --checkpoints {d}", "drop --no-train", "untrained"),
    cli("study", "--workers 0", "--workers=0", "zero-workers"),
    cli("study", "--episode-length nan", "--episode-length=nan", "nan-episode"),
    cli("study", "--detection-range --at-penetration 2", "EnvConfig.penetration=2.0", "penetration-2"),
]
# fmt: on
# fmt: off
COMPARE = [
    cli("compare", "{ckpt} --scenarios nowhere", "unknown scenario 'nowhere'", "unknown-scenario"),
    cli("compare", "{ckpt} --scenarios straight-eval", "held-out", "eval-scenario"),
    cli("compare", "{ckpt} --penetrations 1.5", "EnvConfig.penetration=1.5", "penetration-above-1"),
    cli("compare", "{ckpt} --seeds -1", "--seeds=(-1,)", "negative-seed"),
    cli("compare", "{ckpt} --episode-length nan", "--episode-length=nan", "nan-episode"),
    cli("compare", "{ckpt} --tie -1", "--tie: -1.0 must be >= 0", "negative-tie"),
    cli("compare", "{ckpt} {d}/garbage.pt", "garbage.pt: corrupt or unreadable", "bad-checkpoint"),
    cli("compare", "{d}/emptyrun", "no snapshots/*.pt or auto.pt", "empty-run-folder"),
    cli("compare", "{ckpt} --out {d}/blocker", "--out: cannot use", "out-is-a-file"),
]
# fmt: on
# fmt: off
FLEET = [
    cli("fleet", "--init {d}/garbage.pt --iterations 1", "garbage.pt: corrupt or unreadable",
        "bad-init"),
    cli("fleet", "--iterations 1", "holds no run to resume; give --init", "no-init"),
    cli("fleet", "--init {ckpt} --minutes 0", "give a budget", "no-budget"),
    cli("fleet", "--init {ckpt} --minutes nan", "minutes=nan", "nan-minutes"),
    cli("fleet", "--init {ckpt} --minutes inf", "minutes=inf", "inf-minutes"),
    cli("fleet", "--init {ckpt} --iterations 1 --workers 0", "workers=0", "zero-workers"),
    cli("fleet", "--init {ckpt} --iterations 1 --penetrations 0", "penetrations [0.0]", "zero-penetration"),
    cli("fleet", "--init {ckpt} --iterations 1 --densities -5", "densities [-5.0]", "negative-density"),
    cli("fleet", "--init {ckpt} --iterations 1 --densities 5000", "no density of [5000.0]",
        "density-over-jam"),
    cli("fleet", "--init {ckpt} --iterations 1 --scenarios nowhere", "unknown scenario 'nowhere'",
        "unknown-scenario"),
    cli("fleet", "--init {ckpt} --iterations 1 --seed -1", "seed=-1", "negative-seed"),
    cli("fleet", "--init {ckpt} --iterations 1 --warmup nan", "warmup nan s", "nan-warmup"),
    cli("fleet", "--init {ckpt} --iterations 1 --out {d}/blocker", "--out: cannot use", "out-is-a-file"),
]
# fmt: on
# fmt: off
BENCH = [
    cli("bench", "--section nope", "argument --section: invalid choice: 'nope'", "unknown-section"),
    cli("bench", "--steps 1", "--steps=1 must be at least 2 x --block", "too-few-steps"),
    cli("bench", "--section snapshot --densities nan", "--densities=nan", "nan-density"),
    cli("bench", "--section env --env-density -5", "--env-density=-5.0", "negative-env-density"),
    cli("bench", "--section env --penetrations 2", "--penetrations=[2.0]", "penetration-above-1"),
    cli("bench", "--section env --env-steps 0", "--env-steps=0 must be >= 1", "zero-env-steps"),
    cli("bench", "--section soak --soak-length inf", "--soak-length=inf", "inf-soak"),
    cli("bench", "--section learner --learner-threads 0", "--learner-threads=0", "zero-threads"),
    cli("bench", "--section study --study-episode -1", "--study-episode=-1.0", "negative-study-episode"),
    cli("bench", "--section scale --scale-avs 0", "--scale-avs=0 must be >= 1", "zero-scale-avs"),
    cli("bench", "--section scale --city-grid 1", "--city-grid=1 must be >= 2", "one-junction-city"),
    cli("bench", "--section scale --city-penetration 1.5", "--city-penetration=1.5", "city-share-above-1"),
    cli("bench", "--section soak --json", "--json prints sections", "json-of-soak"),
]
# fmt: on
CLI_CASES = SWEEP + EVALUATE + TRAIN + COMPARE + FLEET + BENCH + STUDY

#: Real processes: a bad input is refused with no traceback at the process level either.
# fmt: off
PROCESS_CASES = [
    pytest.param("sweep", "--seeds -1 --out {out}", "--seeds=(-1,)", id="sweep-process"),
    pytest.param("evaluate", "--policy auto --checkpoint {d}/garbage.pt --out {out}/r.jsonl",
                 "garbage.pt: corrupt or unreadable", id="evaluate-process"),
    pytest.param("train", "--minutes nan --out {out}", "TrainConfig.minutes=nan", id="train-process"),
]
# fmt: on


# --------------------------------------------------------------------------- bad files
def _netgenerate(out: Path) -> Path:
    subprocess.run([binary("netgenerate"), "--grid", "--grid.number", "2", "--grid.length", "200",
                    "-o", str(out)], check=True, capture_output=True, timeout=120)  # fmt: skip
    return out


def _without_car_lanes(net: Path, out: Path) -> Path:
    """``net`` with every lane's permissions changed to bicycles and pedestrians only."""
    tree = ET.parse(net)
    for lane in tree.getroot().iter("lane"):
        lane.attrib.pop("disallow", None)
        lane.set("allow", "bicycle pedestrian")
    tree.write(out)
    return out


class _Unsafe:
    """Pickles as a call of a global function: what a weights-only load must refuse."""

    def __reduce__(self) -> tuple:
        return (print, ("arbitrary code",))


def _save(path: Path, obj: Any) -> None:
    torch.save(obj, path)


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One folder of bad inputs, built once: checkpoints, networks, configurations."""
    d = tmp_path_factory.mktemp("bad_inputs")
    (d / "blocker").write_text("a file where a folder must be")
    (d / "emptyrun").mkdir()
    (d / "road.txt").write_text("not a network")
    # checkpoints
    shipped = torch.load(SHIPPED_CHECKPOINT, map_location="cpu", weights_only=True)
    (d / "garbage.pt").write_bytes(b"not a checkpoint")
    (d / "empty.pt").write_bytes(b"")
    (d / "torn.pt").write_bytes(SHIPPED_CHECKPOINT.read_bytes()[:20000])
    (d / "pickled.pt").write_bytes(pickle.dumps({"learner": {}}))
    _save(d / "keys.pt", {"weights": {}})
    _save(d / "format.pt", {**shipped, "format": "someone-else/1"})
    _save(d / "unsafe.pt", {**shipped, "meta": _Unsafe()})
    _save(d / "learner.pt", {**shipped, "learner": None})
    _save(
        d / "meta.pt", {**shipped, "meta": {k: v for k, v in shipped["meta"].items() if k != "lca"}}
    )
    actor = {k: v[..., :1] if v.ndim else v for k, v in shipped["learner"]["actor"].items()}
    _save(d / "shapes.pt", {**shipped, "learner": {**shipped["learner"], "actor": actor}})
    # scenario files
    (d / "empty.net.xml").write_text("")
    (d / "torn.net.xml").write_text("<net><edge id='a'")
    (d / "routes.net.xml").write_text("<routes/>")
    (d / "noedges.net.xml").write_text("<net/>")
    (d / "garbage.net.xml.gz").write_bytes(gzip.compress(b"\x00\x01 binary garbage"))
    (d / "notgzip.net.xml.gz").write_bytes(b"\x1f\x8b but no gzip stream follows")
    (d / "folder.net.xml").mkdir()
    grid = _netgenerate(d / "grid.net.xml")
    _without_car_lanes(grid, d / "nocars.net.xml")
    (d / "nonet.sumocfg").write_text(
        '<configuration><input><net-file value="missing.net.xml"/></input></configuration>'
    )
    (d / "nonetfile.sumocfg").write_text("<configuration><input/></configuration>")
    (d / "noroutes.sumocfg").write_text(
        '<configuration><input><net-file value="grid.net.xml"/>'
        '<route-files value="missing.rou.xml"/></input></configuration>'
    )
    return d


# --------------------------------------------------------------------------- CLIs
class WorkStarted(AssertionError):
    """A CLI started work (episodes, training, search, a benchmark) before refusing its input."""


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every entry into real work fails the test (and so can never hang it)."""
    from agents.training.trainer import Trainer

    def started(*args: Any, **kwargs: Any) -> None:
        raise WorkStarted("work started before the bad input was refused")

    monkeypatch.setattr(sweep, "run_sweep", started)
    monkeypatch.setattr(compare, "run", started)
    monkeypatch.setattr(evaluate, "run_copies", started)
    monkeypatch.setattr(fleet.FleetSearch, "run", started)
    monkeypatch.setattr(Trainer, "run", started)
    monkeypatch.setattr(study, "train_missing", started)
    monkeypatch.setattr(bench, "section_env", started)
    for name in bench.SECTIONS:
        monkeypatch.setitem(bench.SECTIONS, name, started)


def _expand(argv: list[str], files: Path, out: Path) -> list[str]:
    return [a.format(d=files, out=out, ckpt=CKPT) for a in argv]


def _error_line(err: str, prog: str) -> str:
    """The one ``prog: error:`` line of ``err``; it must be the last line (one line long)."""
    lines = err.rstrip("\n").splitlines()
    errors = [line for line in lines if line.startswith(f"{prog}: error: ")]
    assert len(errors) == 1 and lines[-1] == errors[0], err
    return errors[0]


@pytest.mark.parametrize(("name", "argv", "needle", "keep"), CLI_CASES)
def test_cli_refuses_a_bad_input_before_any_work(
    name: str, argv: list[str], needle: str, keep: bool, files: Path, tmp_path: Path,
    capsys: pytest.CaptureFixture, no_work: None,
) -> None:  # fmt: skip
    out = tmp_path / "out"
    records = out / "records.jsonl"
    if keep:
        out.mkdir()
        records.write_bytes(RECORD)
    with pytest.raises(SystemExit) as stop:
        MODULE[name].main(_expand(argv, files, out))
    err = capsys.readouterr().err
    assert stop.value.code == 2, err
    assert "Traceback" not in err
    assert needle in _error_line(err, PROG[name])
    written = [p for p in out.rglob("*") if p.is_file() and p != records] if out.exists() else []
    assert written == [], "files written before the error"
    if keep:
        assert records.read_bytes() == RECORD, "an existing records file changed"


@pytest.mark.parametrize(("name", "argv", "needle"), PROCESS_CASES)
def test_a_real_process_prints_one_line_and_no_traceback(
    name: str, argv: str, needle: str, files: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    command = [sys.executable, "-m", f"mixed_traffic.{name}", *_expand(argv.split(), files, out)]
    proc = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert needle in _error_line(proc.stderr, PROG[name])
    assert not out.exists() or not [p for p in out.rglob("*") if p.is_file()]


# --------------------------------------------------------------------------- scenario files
# fmt: off
SCENARIO_FILES = [
    pytest.param("missing.net.xml", "missing.net.xml does not exist", id="missing-file"),
    pytest.param("empty.net.xml", "empty.net.xml is malformed XML", id="empty-file"),
    pytest.param("torn.net.xml", "torn.net.xml is malformed XML", id="truncated-xml"),
    pytest.param("garbage.net.xml.gz", "garbage.net.xml.gz is malformed XML", id="gzipped-garbage"),
    pytest.param("notgzip.net.xml.gz", "notgzip.net.xml.gz is malformed XML", id="not-gzip"),
    pytest.param("routes.net.xml", "is not a SUMO network (root <routes>", id="wrong-root"),
    pytest.param("noedges.net.xml", "noedges.net.xml contains no edges", id="no-edges"),
    pytest.param("nocars.net.xml", "nocars.net.xml has no lane that passenger cars may use",
                 id="netgenerate-without-car-lanes"),
    pytest.param("folder.net.xml", "folder.net.xml is a folder, not a file", id="a-folder"),
    pytest.param("nonet.sumocfg", "missing.net.xml does not exist", id="sumocfg-missing-net"),
    pytest.param("nonetfile.sumocfg", "nonetfile.sumocfg has no net-file", id="sumocfg-no-net-file"),
    pytest.param("noroutes.sumocfg", "route file", id="sumocfg-missing-route-file"),
]
# fmt: on


@pytest.mark.parametrize(("name", "needle"), SCENARIO_FILES)
def test_a_bad_scenario_file_is_named(name: str, needle: str, files: Path) -> None:
    with pytest.raises(ValueError) as refused:
        load_scenario(str(files / name))
    message = str(refused.value)
    assert needle in message and len(message.splitlines()) == 1, message


# --------------------------------------------------------------------------- checkpoints
# fmt: off
CHECKPOINTS = [
    pytest.param("garbage.pt", {}, "garbage.pt: corrupt or unreadable", id="garbage-bytes"),
    pytest.param("empty.pt", {}, "empty.pt: corrupt or unreadable", id="empty-file"),
    pytest.param("torn.pt", {}, "torn.pt: corrupt or unreadable", id="truncated"),
    pytest.param("pickled.pt", {}, "pickled.pt: corrupt or unreadable", id="plain-pickle"),
    pytest.param("unsafe.pt", {}, "unsafe.pt: corrupt or unreadable", id="unsafe-global"),
    pytest.param("keys.pt", {}, "keys.pt: not an RBP-DQN checkpoint", id="wrong-keys"),
    pytest.param("format.pt", {}, "format.pt: format 'someone-else/1'", id="wrong-format"),
    pytest.param("learner.pt", {}, "learner.pt: 'learner' is a NoneType", id="learner-not-a-dict"),
    pytest.param("meta.pt", {}, "meta.pt: invalid meta ('lca')", id="meta-without-lca"),
    pytest.param("shapes.pt", {}, "shapes.pt: state does not fit the model", id="wrong-shapes"),
    pytest.param(CKPT, {"z": 3}, "observation/model config mismatch", id="history-mismatch"),
    pytest.param("emptyrun", {}, "emptyrun: file not found", id="a-folder"),
]
# fmt: on


@pytest.mark.parametrize(("name", "kwargs", "needle"), CHECKPOINTS)
def test_the_agent_loader_names_a_bad_checkpoint(
    name: str, kwargs: dict, needle: str, files: Path
) -> None:
    with pytest.raises(ValueError) as refused:
        make_policy("auto", checkpoint=files / name, **kwargs)
    message = str(refused.value)
    assert needle in message and len(message.splitlines()) == 1, message


# --------------------------------------------------------------------------- env config
def _raises(make: Callable[[], Any], kind: type[Exception], needle: str) -> None:
    with pytest.raises(kind) as refused:
        make()
    message = str(refused.value)
    assert needle in message and len(message.splitlines()) == 1, message


# fmt: off
ENV_CONFIG = [
    pytest.param(lambda: EnvConfig(density=-5.0), "EnvConfig.density=-5.0", id="negative-density"),
    pytest.param(lambda: EnvConfig(penetration=1.5), "EnvConfig.penetration=1.5", id="penetration-1.5"),
    pytest.param(lambda: EnvConfig(step_length=math.nan), "EnvConfig.step_length=nan", id="nan-step"),
    pytest.param(lambda: EnvConfig(episode_length=0.0), "EnvConfig.episode_length=0.0", id="zero-episode"),
    pytest.param(lambda: EnvConfig(episode_length=0.05), "shorter than one step", id="episode-under-a-step"),
    pytest.param(lambda: EnvConfig(weather="snow"), "EnvConfig.weather='snow'", id="unknown-weather"),
    pytest.param(lambda: EnvConfig(weather="Rain"), "EnvConfig.weather='Rain'", id="capitalised-weather"),
    pytest.param(lambda: EnvConfig(seed=1.5), "EnvConfig.seed=1.5", id="fractional-seed"),
    pytest.param(lambda: EnvConfig(sensors=5), "EnvConfig.sensors=5 must be a SensorConfig", id="sensors-int"),
    pytest.param(lambda: EnvConfig(fixed_fleet="yes"), "EnvConfig.fixed_fleet='yes' must be True or False",
                 id="fixed-fleet-string"),
    pytest.param(lambda: EnvConfig(av_window=0.0), "EnvConfig.av_window=0.0", id="zero-av-window"),
    pytest.param(lambda: SensorConfig(history=1.5), "SensorConfig.history=1.5", id="fractional-history"),
    pytest.param(lambda: SensorConfig(noise="no"), "SensorConfig.noise='no' must be True or False",
                 id="noise-string"),
    pytest.param(lambda: HumanConfig(car_following="Krauss"), "HumanConfig.car_following='Krauss'",
                 id="unknown-car-following"),
    pytest.param(lambda: EnvConfig.from_dict({"densty": 60}), "unknown EnvConfig fields ['densty']",
                 id="from-dict-typo"),
    pytest.param(lambda: parallel_env(scenario="nowhere"), "unknown scenario 'nowhere'", id="unknown-scenario"),
    pytest.param(lambda: parallel_env(density=900.0), "density=900.0 veh/km is outside", id="over-jam-density"),
    pytest.param(lambda: parallel_env(render_mode="video"), "render_mode='video'", id="unknown-render-mode"),
    pytest.param(lambda: MixedTrafficEnv(warmup=200.0, episode_length=100.0), "warmup=200.0 s",
                 id="warmup-past-the-end"),
]
# fmt: on


@pytest.mark.parametrize(("make", "needle"), ENV_CONFIG)
def test_a_bad_env_config_is_named_before_sumo_starts(make: Callable, needle: str) -> None:
    _raises(make, ValueError, needle)


# --------------------------------------------------------------------------- env API
def _follow(agents: list[str]) -> dict[str, dict]:
    return {a: {"decision": 1, "params": np.zeros((3, 2), np.float32)} for a in agents}


def _env(**kw: Any) -> MixedTrafficEnv:
    return MixedTrafficEnv(config=EnvConfig(density=60.0, penetration=0.5, **kw))


def _step_before_reset() -> None:
    _env().step({})


def _metrics_before_reset() -> None:
    _env().episode_metrics()


def _step_after_close() -> None:
    env = _env(episode_length=5.0)
    env.reset(seed=0)
    env.close()
    env.step({})


def _step_after_the_end() -> None:
    env = _env(episode_length=0.3)
    try:
        env.reset(seed=0)
        while env.agents:
            env.step(_follow(env.agents))
        env.step({})
    finally:
        env.close()


# fmt: off
ENV_PHASES = [
    pytest.param(_step_before_reset, r"step() before reset()", id="step-before-reset"),
    pytest.param(_metrics_before_reset, "episode_metrics() before reset()", id="metrics-before-reset"),
    pytest.param(_step_after_close, "step() after close()", id="step-after-close"),
    pytest.param(_step_after_the_end, "after the episode ended", id="step-after-the-end"),
]
# fmt: on


@pytest.mark.parametrize(("misuse", "needle"), ENV_PHASES)
def test_the_env_api_out_of_order_is_named(misuse: Callable, needle: str) -> None:
    _raises(misuse, RuntimeError, needle)


@pytest.fixture(scope="module")
def live_env() -> Iterator[MixedTrafficEnv]:
    """One env after reset, shared by the bad actions (each must leave it where it was)."""
    env = _env(episode_length=30.0)
    env.reset(seed=0)
    assert env.agents
    yield env
    env.close()


def _with(agents: list[str], **action: Any) -> dict:
    """Follow for every agent, the first one's action changed by ``action``."""
    actions = _follow(agents)
    actions[agents[0]] = {**actions[agents[0]], **action}
    return actions


# fmt: off
ACTIONS = [
    pytest.param(lambda a: None, "step() takes a dict of actions", id="none"),
    pytest.param(lambda a: [1, 0.5], "step() takes a dict of actions, one per live agent (agent id "
                 "-> {'decision', 'params'}), got list", id="a-list"),
    pytest.param(lambda a: {**_follow(a), "av_99999": _follow(a)[a[0]]},
                 "not live: ['av_99999']", id="unknown-agent"),
    pytest.param(lambda a: {k: v for k, v in _follow(a).items() if k != a[0]},
                 "no action for live agent", id="missing-agent"),
    pytest.param(lambda a: _with(a, params=np.full((3, 2), np.nan)), "(left_change, steering) is not "
                 "finite (nan)", id="nan-params"),
    pytest.param(lambda a: _with(a, params=np.full((3, 2), np.inf)), "is not finite (inf)", id="inf-params"),
    pytest.param(lambda a: _with(a, params=np.full((3, 2), 2.0)), "'params'[0, 0]=2.0", id="params-off-the-box"),
    pytest.param(lambda a: _with(a, params=np.zeros(2)), "'params' has shape (2,), expected (3, 2)",
                 id="params-wrong-shape"),
    pytest.param(lambda a: _with(a, decision=3), "'decision'=3 is outside the space", id="decision-3"),
    pytest.param(lambda a: _with(a, decision=1.5), "'decision'=1.5 is not an integer", id="decision-1.5"),
    pytest.param(lambda a: _with(a, decision="left"), "'decision'='left' is not an integer",
                 id="decision-string"),
    pytest.param(lambda a: {**_follow(a), a[0]: [1, 0.0, 0.0]}, "must be a dict with keys 'decision' "
                 "and 'params'", id="action-not-a-dict"),
]
# fmt: on


@pytest.mark.parametrize(("make", "needle"), ACTIONS)
def test_a_bad_action_is_named_and_nothing_moves(
    make: Callable, needle: str, live_env: MixedTrafficEnv
) -> None:
    before = (live_env.sim_time, list(live_env.agents))
    _raises(lambda: live_env.step(make(list(live_env.agents))), ValueError, needle)
    assert (live_env.sim_time, list(live_env.agents)) == before


# fmt: off
RESETS = [
    pytest.param({"seed": -1}, "reset(seed=-1): seed must be an integer >= 0", id="negative-seed"),
    pytest.param({"seed": 1.5}, "reset(seed=1.5)", id="fractional-seed"),
    pytest.param({"seed": "x"}, "reset(seed='x')", id="string-seed"),
    pytest.param({"seed": 0, "options": ["allow_no_agents"]}, "reset(options=['allow_no_agents'])",
                 id="options-not-a-dict"),
]
# fmt: on


@pytest.mark.parametrize(("kwargs", "needle"), RESETS)
def test_bad_reset_arguments_are_named(
    kwargs: dict, needle: str, live_env: MixedTrafficEnv
) -> None:
    before = live_env.sim_time
    _raises(lambda: live_env.reset(**kwargs), ValueError, needle)
    assert live_env.sim_time == before  # the episode was not restarted


# --------------------------------------------------------------------------- the tally
TALLY = {
    "sweep CLI": len(SWEEP) + 1,
    "evaluate CLI": len(EVALUATE) + 1,
    "train CLI": len(TRAIN) + 1,
    "compare CLI": len(COMPARE),
    "fleet CLI": len(FLEET),
    "bench CLI": len(BENCH),
    "study CLI": len(STUDY),
    "env API": len(ENV_PHASES) + len(ACTIONS) + len(RESETS),
    "env config": len(ENV_CONFIG),
    "scenario files": len(SCENARIO_FILES),
    "checkpoints": len(CHECKPOINTS),
}


def test_the_tally_counts_every_case() -> None:
    assert sum(TALLY.values()) >= 95, TALLY
    assert sum(TALLY.values()) == len(CLI_CASES) + len(PROCESS_CASES) + sum(
        TALLY[k] for k in ("env API", "env config", "scenario files", "checkpoints")
    )
