"""The package's layout is its architecture: data flows one way through the stages, commands never import
each other, and the layers that must stay light (core, the hardware plugins) do.

Every `import lerobot_condground...` in every module is read from the source (module level and the lazy
imports inside functions alike), so a reach-back cannot hide behind a deferred import.
"""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "lerobot_condground"
# Folders of the installed package: the three fixed top-level pillars are mapped into it.
FOLDERS = {"envs": ROOT / "envs", "policies": ROOT / "policies", "processors": ROOT / "processors"}

# The pipeline, bottom to top: a module may import its own stage and the stages of lower rank only. Stages of
# equal rank are siblings and may not import each other.
RANKS = {
    "core": 0,  # names and data every stage shares
    "envs": 1,  # scene spec, env, expert
    "processors": 2,
    "labelling": 2,  # per-sample transforms; hardware prompts and labels
    "datasets": 3,
    "cameras": 3,  # demonstrations; cameras
    "policies": 4,
    "robots": 4,
    "teleoperators": 5,
    "evaluation": 6,
    "diagnosis": 7,
    "bench": 8,
    "experiments": 9,  # whole studies run as commands of every stage
    "scripts": 10,
    "registration": 11,
    "cli": 12,
}
# Modules that implement one command: only the command layer (scripts, bench, cli) may import them.
COMMAND_MODULES = {
    "datasets.record",
    "datasets.augment",
    "datasets.merge",
    "evaluation.sweep",
    "evaluation.subgoals",
    "diagnosis.diagnose",
    "diagnosis.probe",
    "diagnosis.attention",
    "diagnosis.report",
    "labelling.prompts",
}
COMMAND_LAYER = {"scripts", "bench", "experiments", "cli"}


def _modules() -> dict[str, Path]:
    """dotted name inside the package (e.g. `evaluation.sweep`) -> source file."""
    found = {}
    for path in (ROOT / PACKAGE).rglob("*.py"):
        found[".".join(path.relative_to(ROOT / PACKAGE).with_suffix("").parts)] = path
    for stage, folder in FOLDERS.items():
        for path in folder.rglob("*.py"):
            found[".".join((stage, *path.relative_to(folder).with_suffix("").parts))] = path
    return {
        "" if name == "__init__" else name.removesuffix(".__init__"): path for name, path in found.items()
    }


def _imports(name: str, path: Path) -> set[str]:
    """Every module of the package that `name` imports, as dotted names inside the package."""
    is_package = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")[: len(name.split(".")) - node.level + is_package]
                module = ".".join([PACKAGE, *base, *([node.module] if node.module else [])])
            else:
                module = node.module or ""
            targets = [module] + [f"{module}.{alias.name}" for alias in node.names]
        else:
            continue
        out |= {t.removeprefix(f"{PACKAGE}.") for t in targets if t.startswith(f"{PACKAGE}.")}
    return out


def _stage(name: str) -> str:
    return name.split(".")[0]


def test_every_module_has_a_stage():
    assert {_stage(name) for name in _modules() if name} <= set(RANKS)


def test_data_flows_one_way_and_commands_do_not_import_each_other():
    modules = _modules()
    known = set(modules)
    problems = []
    for name, path in sorted(modules.items()):
        if not name:
            continue
        stage = _stage(name)
        for target in sorted(t for t in _imports(name, path) if t in known and t):
            other = _stage(target)
            if other != stage and RANKS[other] >= RANKS[stage]:
                problems.append(f"{name} imports {target} ({other} is not below {stage})")
            if target in COMMAND_MODULES and stage not in COMMAND_LAYER and target != name:
                problems.append(f"{name} imports the command module {target}")
            if stage == "scripts" and other == "scripts" and target != "scripts":
                problems.append(f"{name} imports another command's script {target}")
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize(
    "modules, banned",
    [
        (
            ["core.conditions", "core.labels", "core.configs", "core.paper", "core.provenance", "core.ur3e"],
            ["mujoco", "torch", "lerobot"],
        ),
        (
            [
                "robots.config_ur3e",
                "robots.ur3e",
                "robots.rtde_arm",
                "robots.kinematics",
                "robots.safety",
                "teleoperators.config_ur3e_teleops",
                "teleoperators.ur3e_teleops",
                "cameras.config_ur3e_twin",
            ],
            ["mujoco"],
        ),
    ],
)
def test_light_layers_stay_light(modules, banned):
    code = "import sys\n" + "".join(f"import {PACKAGE}.{m}\n" for m in modules)
    code += f"print([m for m in {banned!r} if m in sys.modules])\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out
