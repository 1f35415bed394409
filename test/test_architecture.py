"""The layers hold: the import contracts of ``.importlinter`` are kept, and they do fail
when a core module imports rclpy or the ROS layer; the table of nodes is what is installed."""
from __future__ import annotations

import importlib
import importlib.metadata
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from experiment_runner.ros.nodes import JOINING, NODE_NAMES, NODES, console_scripts, node, publisher_of

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("stage_sim", "stage_control", "msg_defs", "experiment_runner")
LINT = Path(sys.executable).parent / "lint-imports"


def _lint(cwd: Path) -> subprocess.CompletedProcess:
    """``lint-imports`` on the packages found in ``cwd`` with the contracts of ``cwd/.importlinter``."""
    env = {**os.environ, "PYTHONPATH": str(cwd)}
    return subprocess.run([str(LINT), "--config", str(cwd / ".importlinter"), "--no-cache"], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def test_the_import_contracts_are_kept():
    out = _lint(ROOT)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "BROKEN" not in out.stdout and " 0 broken" in out.stdout


@pytest.fixture
def source_copy(tmp_path):
    """The four packages' Python files and the contracts, copied to ``tmp_path``."""
    for pkg in PACKAGES:
        shutil.copytree(ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("*.yaml", "__pycache__", "*.md"))
    shutil.copy(ROOT / ".importlinter", tmp_path / ".importlinter")
    return tmp_path


@pytest.mark.parametrize("module, line, broken", [
    ("stage_sim/plant.py", "import rclpy", ["Only the ROS layer imports rclpy"]),
    ("experiment_runner/core/recording/writer.py", "from rclpy.serialization import serialize_message",
     ["Only the ROS layer imports rclpy"]),
    ("msg_defs/convert.py", "from experiment_runner.ros.node import StageNode", ["Layers: the applications above the ROS layer"]),
    ("experiment_runner/ros/servo_node.py", "from experiment_runner.ros.plant_node import PlantNode",
     ["no node imports another"]),
    ("msg_defs/topics.py", "from msg_defs.convert import stamp_ns", ["msg_defs: conversions above"]),
    pytest.param("experiment_runner/core/batch.py", "from experiment_runner.apps.campaigns.spec import Campaign",
                 ["Layers: the applications above the ROS layer"], marks=pytest.mark.slow),
    pytest.param("experiment_runner/apps/campaigns/spec.py", "from experiment_runner.apps.campaigns.runner import run_campaign",
                 ["Campaigns: CLI above runner", "No import cycles"], marks=pytest.mark.slow),
    pytest.param("experiment_runner/apps/diagnosis/openloop.py", "from experiment_runner.apps.diagnosis.predict import replay",
                 ["Diagnosis: command line above", "No import cycles among the modules of any package"],
                 marks=pytest.mark.slow),
    pytest.param("experiment_runner/apps/diagnosis/effects/base.py", "from experiment_runner.apps.diagnosis.effects.friction "
                 "import F_C_NOMINAL", ["Diagnosis effects: the families above"], marks=pytest.mark.slow),
    pytest.param("experiment_runner/apps/design/sweep.py", "from experiment_runner.apps.design.advice import recommend",
                 ["Design advisor: CLI above", "No import cycles among the modules of any package"],
                 marks=pytest.mark.slow),
    pytest.param("experiment_runner/apps/diagnosis/power/cases.py",
                 "from experiment_runner.apps.diagnosis.power.study import run_power",
                 ["Power study: the study above", "No import cycles among the modules of any package"],
                 marks=pytest.mark.slow),
    pytest.param("experiment_runner/apps/design/sweep.py", "from experiment_runner.apps.paper.fi_design import claims",
                 ["The applications are independent"], marks=pytest.mark.slow),
    pytest.param("experiment_runner/apps/campaigns/spec.py", "from experiment_runner.apps.cli import main",
                 ["Applications: the command line above"], marks=pytest.mark.slow),
])
def test_a_broken_layer_breaks_its_contract(source_copy, module, line, broken):
    path = source_copy / module
    path.write_text(path.read_text() + f"\n{line}  # the violation under test\n")
    out = _lint(source_copy)
    assert out.returncode != 0
    report = out.stdout.split("Broken contracts")[-1]
    for name in broken:
        assert name in report, out.stdout
    assert module.replace("/", ".").removesuffix(".py") in report


def test_the_node_table_is_what_setup_installs():
    scripts = {ep.name: ep.value for ep in importlib.metadata.entry_points(group="console_scripts")
               if ep.dist is not None and ep.dist.name == "nanostage"}
    for entry in console_scripts():
        name, target = (part.strip() for part in entry.split("="))
        assert scripts.get(name) == target, f"{name}: installed {scripts.get(name)!r}, table {target!r} " \
                                            "(re-run scripts/bootstrap.sh)"
        assert (Path(sys.executable).parent / name).exists()
    assert set(scripts) == set(NODE_NAMES) | {"nanostage"}


def test_the_node_table_names_each_node_class_and_its_topics():
    for spec in NODES:
        mod = importlib.import_module(spec.module)
        assert callable(mod.main)
        assert getattr(mod, spec.cls).__module__ == spec.module
    assert NODE_NAMES[-1] == "experiment_sequencer"             # started last: it starts the run
    assert "experiment_sequencer" not in JOINING and "recorder" in JOINING
    assert publisher_of("/stage/measured") == "plant_sim" and publisher_of("/sai/command") == "sai_manager"
    with pytest.raises(KeyError, match="known: plant_sim"):
        node("plant_simulator")


def _private_imports(root: Path) -> list[str]:
    """``file:line module name`` of every private name (``_x``, not dunder) a project module imports
    from another project module."""
    import ast
    found = []
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            tree = ast.parse(path.read_text(), filename=str(path))
            for n in ast.walk(tree):
                if isinstance(n, ast.ImportFrom) and (n.level or (n.module or "").split(".")[0] in PACKAGES):
                    found += [f"{path.relative_to(root)}:{n.lineno} {n.module} {a.name}" for a in n.names
                              if a.name.startswith("_") and not a.name.startswith("__")]
    return found


def test_no_private_name_is_imported_across_modules(tmp_path):
    """A name another module needs is public (documented, part of its module's interface); the scan
    finds one planted in a copy."""
    assert _private_imports(ROOT) == []
    pkg = tmp_path / "stage_sim"
    pkg.mkdir()
    (pkg / "planted.py").write_text("from stage_sim.plant import _helper\n")
    for other in PACKAGES[1:]:
        (tmp_path / other).mkdir()
    assert _private_imports(tmp_path) == ["stage_sim/planted.py:1 stage_sim.plant _helper"]


FILE_LINES, CLASS_LINES, FUNCTION_LINES = 800, 400, 120
"""The largest units a reader takes in whole: no module over 800 lines, no class over 400, no
function over 120 (compiled kernels excepted: a numba loop nest is one function by design)."""


def _compiled(fn) -> bool:
    import ast
    names = {ast.unparse(d.func if isinstance(d, ast.Call) else d) for d in fn.decorator_list}
    return any(n.split(".")[-1] in ("njit", "jit", "vectorize", "guvectorize", "cfunc") for n in names)


def _oversized(root: Path) -> list[str]:
    """``path: kind name (lines)`` of every unit over its limit in the packages under ``root``."""
    import ast
    found = []
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            src = path.read_text()
            rel = path.relative_to(root)
            if src.count("\n") > FILE_LINES:
                found.append(f"{rel}: file ({src.count(chr(10))} lines)")
            for n in ast.walk(ast.parse(src)):
                size = getattr(n, "end_lineno", 0) - getattr(n, "lineno", 0) + 1
                if isinstance(n, ast.ClassDef) and size > CLASS_LINES:
                    found.append(f"{rel}: class {n.name} ({size} lines)")
                elif (isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and size > FUNCTION_LINES
                      and not _compiled(n)):
                    found.append(f"{rel}: function {n.name} ({size} lines)")
    return found


def test_no_unit_is_larger_than_a_reader_takes_in(tmp_path):
    assert _oversized(ROOT) == []
    for pkg in PACKAGES:
        (tmp_path / pkg).mkdir()
    body = "\n".join(f"    x{i} = {i}" for i in range(FUNCTION_LINES))
    (tmp_path / "stage_sim" / "big.py").write_text(f"def long():\n{body}\n\n\n@njit\ndef kernel():\n{body}\n")
    assert _oversized(tmp_path) == [f"stage_sim/big.py: function long ({FUNCTION_LINES + 1} lines)"]
