"""The package's shape: documented commands answer --help, no import circles, libsumo and torch
load only where they are needed, and modules stay small."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = ("sweep", "study", "evaluate", "train", "compare", "bench", "report", "scenario",
            "experiments.safety_matrix", "experiments.fleet", "benchmark", "benchmark.ppo")  # fmt: skip


def _python(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=ROOT,
                          timeout=120)  # fmt: skip


def _modules(*folders: str, root: Path = ROOT) -> dict[str, Path]:
    """Module name -> file of every module under ``folders``."""
    files = [f for d in folders for f in sorted((root / d).rglob("*.py"))]
    return {".".join(f.relative_to(root).with_suffix("").parts).removesuffix(".__init__"): f
            for f in files}  # fmt: skip


@pytest.mark.parametrize("command", COMMANDS)
def test_every_documented_command_answers_help(command: str) -> None:
    out = _python("-m", f"mixed_traffic.{command}", "--help")
    assert out.returncode == 0, out.stderr
    assert "usage:" in out.stdout


def _imports(module: str, path: Path, known: set[str]) -> set[str]:
    """Project modules that ``module`` imports anywhere in its file (functions included)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*up, base] if base else up)
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        for name in names:
            while name and name not in known:
                name = name.rpartition(".")[0]
            if name and name != module and not module.startswith(name + "."):
                found.add(name)
    return found


def _circles(root: Path, *folders: str) -> list[str]:
    """Modules that import themselves through a chain of project imports."""
    paths = _modules(*folders, root=root)
    graph = {m: _imports(m, p, set(paths)) for m, p in paths.items()}

    def reaches(start: str) -> bool:
        seen, todo = set(), list(graph[start])
        while todo:
            m = todo.pop()
            if m == start:
                return True
            if m not in seen:
                seen.add(m)
                todo += graph.get(m, ())
        return False

    return sorted(m for m in graph if reaches(m))


def test_the_circle_check_finds_a_circle(tmp_path: Path) -> None:
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "a.py").write_text("from pkg.b import x\n")
    (tmp_path / "pkg" / "b.py").write_text("def x():\n    from pkg import a\n")
    (tmp_path / "pkg" / "c.py").write_text("import pkg.a\n")
    assert _circles(tmp_path, "pkg") == ["pkg.a", "pkg.b"]


def test_no_import_circles() -> None:
    assert _circles(ROOT, "mixed_traffic", "agents", "analysis") == []


#: agents/ from the ground up, the way TorchRL keeps nets, losses, collectors and trainers apart:
#: each layer imports only layers before it.
AGENT_LAYERS = (("agents.rules", "agents.nets"), ("agents.learners",),
                ("agents.longitudinal", "agents.ppo_policy", "agents.driver"), ("agents.checkpoint",),
                ("agents.policies",), ("agents.collection",), ("agents.training",),
                ("agents.bench_inference", "agents.bench_learner"))  # fmt: skip


def _layer(module: str) -> int | None:
    for i, layer in enumerate(AGENT_LAYERS):
        if any(module == p or module.startswith(p + ".") for p in layer):
            return i
    return None


def test_agents_import_only_the_layers_below() -> None:
    paths = {m: p for m, p in _modules("agents").items() if m != "agents"}
    assert [m for m in paths if _layer(m) is None] == []  # a new module takes its place
    upward = [f"{m} -> {dep}" for m, path in paths.items()
              for dep in _imports(m, path, set(paths)) if _layer(dep) > _layer(m)]  # fmt: skip
    assert upward == []


_PROBE = """
import importlib, os, sys
heavy, preload, modules = sys.argv[1], sys.argv[2].split(","), sys.argv[3:]
for name in filter(None, preload):  # third-party packages, shared by every forked child
    importlib.import_module(name)
assert heavy not in sys.modules, f"preloading {preload} loaded {heavy}"
bad = []
for m in modules:  # each in a fork of this interpreter: no project module loaded yet
    r, w = os.pipe()
    if os.fork() == 0:
        try:
            importlib.import_module(m)
            answer = b"0" if heavy not in sys.modules else b"1"
        except BaseException:
            answer = b"1"
        os.write(w, answer)
        os._exit(0)
    os.close(w)
    if os.read(r, 1) != b"0":
        bad.append(m)
    os.close(r)
    os.wait()
print("\\n".join(bad))
"""

#: Third-party packages preloaded before the forks (a fresh interpreter per module took 50 s);
#: none of them loads libsumo, and torch is left out when torch is what is looked for.
_PRELOAD = ("numpy", "pandas", "matplotlib.pyplot", "seaborn", "gymnasium", "pettingzoo",
            "sumolib", "tqdm", "torch")  # fmt: skip


def _loaded_after_import(modules: list[str], heavy: str) -> list[str]:
    """The modules whose import loads ``heavy``, each checked in a fork of an interpreter that
    has loaded only third-party packages other than ``heavy``."""
    preload = ",".join(p for p in _PRELOAD if p.split(".")[0] != heavy)
    out = _python("-c", _PROBE, heavy, preload, *modules)
    assert out.returncode == 0, out.stderr
    return [line for line in out.stdout.splitlines() if line]


def test_libsumo_loads_only_when_a_simulation_starts() -> None:
    assert _loaded_after_import(["libsumo"], "libsumo") == ["libsumo"]  # the probe sees it
    modules = list(_modules("mixed_traffic", "agents", "analysis"))
    loading = _loaded_after_import(modules, "libsumo")
    assert len(loading) <= len(modules) // 4, loading


def test_analysis_loads_neither_libsumo_nor_torch() -> None:
    modules = list(_modules("analysis"))
    assert _loaded_after_import(modules, "libsumo") == []
    assert _loaded_after_import(modules, "torch") == []


def test_no_module_is_over_600_lines() -> None:
    files = [f for d in ("mixed_traffic", "agents", "analysis") for f in (ROOT / d).rglob("*.py")]
    lines = {f.relative_to(ROOT).as_posix(): len(f.read_text().splitlines()) for f in files}
    assert {f: n for f, n in lines.items() if n > 600} == {}


def test_pyproject_lists_every_package_folder() -> None:
    import tomllib

    listed = set(
        tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    )
    folders = {".".join(f.parent.relative_to(ROOT).parts)
               for d in ("mixed_traffic", "agents", "analysis") for f in (ROOT / d).rglob("*.py")}  # fmt: skip
    assert listed == folders | {"agents.checkpoints", "mixed_traffic._scenarios"}


def test_a_wheel_install_runs_the_shipped_scenarios_from_any_folder(tmp_path: Path) -> None:
    """Issue 25 D2: scenarios/ ships inside the wheel (mapped to mixed_traffic/_scenarios)."""
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps",
                            "--no-build-isolation", "-q", "-w", str(tmp_path / "dist")],
                           capture_output=True, text=True, cwd=tmp_path, timeout=300)  # fmt: skip
    assert build.returncode == 0, build.stderr[-2000:]
    (wheel,) = (tmp_path / "dist").glob("*.whl")
    site, elsewhere = tmp_path / "site", tmp_path / "elsewhere"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target",
                    str(site), str(wheel)], check=True, timeout=300)  # fmt: skip
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("MIXED_TRAFFIC_")}
    env |= {"PYTHONPATH": str(site), "MIXED_TRAFFIC_CACHE": str(tmp_path / "cache")}
    script = (
        "import json, mixed_traffic as m; from mixed_traffic.paths import SCENARIOS_DIR as s;"
        "print(json.dumps([m.__file__, str(s), m.list_scenarios()]))"
    )
    where = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                           cwd=elsewhere, env=env, timeout=120)  # fmt: skip
    assert where.returncode == 0, where.stderr
    module, scenarios, names = json.loads(where.stdout)
    assert module.startswith(str(site)) and scenarios.startswith(str(site))
    assert {"straight", "ring", "urban"} <= {n.split("-")[0] for n in names}
    run = subprocess.run([sys.executable, "-m", "mixed_traffic.evaluate", "--policy", "acc-lc",
                          "--scenario", "straight", "--seeds", "0", "--episode-length", "10",
                          "--warmup", "0", "--json"],
                         capture_output=True, text=True, cwd=elsewhere, env=env, timeout=300)  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
    assert '"policy"' in run.stdout
    from mixed_traffic.schema import STUDY_POLICIES

    shipped = {p.stem for p in (site / "agents" / "checkpoints" / "study").glob("*.pt")}
    assert shipped == set(STUDY_POLICIES)
