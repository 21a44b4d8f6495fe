"""Each role imports only what it needs: the entry point of each, imported in a fresh interpreter,
must not load the heavy modules of another role (docs/architecture.md, "Roles")."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "torchvision", "bpy", "numba", "cv2")

# Every module of the core package, so a new one is checked too.
CORE_MODULES = sorted(f"foldwise.{path.stem}" for path in (ROOT / "foldwise").glob("*.py") if path.stem != "__init__")

# role: (modules its process imports, a statement it runs, heavy modules it must not load)
ROLES = {
    "foldwise core": (
        CORE_MODULES,
        # Sampling θ needs the asset names only, not the images behind them.
        "from foldwise.sampling import generate_parameters; generate_parameters('fb', 'easy', 4, seed=0); "
        "generate_parameters('mixed', 'hard', 4, seed=0)",
        ("torch", "torchvision", "bpy", "numba", "cv2"),
    ),
    "scheduler": (
        ["services.scheduler.service", "services.scheduler.reconcile", "services.scheduler.stopping"],
        # As the scheduler samples a stage: θ from the config's asset names.
        "from foldwise.config import load_config; from foldwise.sampling import generate_parameters; "
        "config = load_config('configs/quick.yaml'); "
        "generate_parameters('mixed', 'hard', 4, seed=0, assets=config.assets, mixed=config.mixed_draw())",
        ("torch", "torchvision", "bpy", "numba", "cv2"),
    ),
    "api": (
        ["services.api.app"],
        "",
        ("torch", "torchvision", "bpy", "numba", "cv2"),
    ),
    "render worker": (
        ["workers.app", "workers.render.tasks", "workers.render.pipeline", "workers.render.assets"],
        "",
        ("torch", "torchvision"),
    ),
    "train worker": (
        [
            "workers.app",
            "workers.train.tasks",
            "workers.train.training",
            "workers.train.checkpoint",
            "workers.train.evaluation",
        ],
        "",
        ("bpy",),
    ),
}


def _loaded(modules: list[str], statement: str) -> set[str]:
    script = (
        "import importlib, json, sys\n"
        f"for name in {modules!r}:\n"
        "    importlib.import_module(name)\n"
        f"{statement}\n"
        f"print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))\n"
    )
    result = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    return set(json.loads(result.stdout.strip().splitlines()[-1]))


@pytest.mark.parametrize("role", list(ROLES))
def test_role_loads_no_heavy_module_of_another(role: str) -> None:
    modules, statement, forbidden = ROLES[role]
    loaded = _loaded(modules, statement)
    assert not loaded & set(forbidden), f"{role} loaded {sorted(loaded & set(forbidden))}"


def test_core_and_services_import_no_worker_package() -> None:
    """foldwise/ and services/scheduler/ send tasks by name (workers.app) and never import the
    render or train worker's code."""
    offenders = []
    for folder in ("foldwise", "services/scheduler"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                code = line.split("#", 1)[0]
                if ("import" in code) and ("workers.render" in code or "workers.train" in code):
                    offenders.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


def test_no_test_module_imports_another():
    """Shared fixtures live in conftest.py and helpers in modules of their own: a test module
    imported by another would run its tests' collection twice and tie unrelated tests together."""
    import ast

    offenders = []
    for path in sorted((ROOT / "tests").rglob("test_*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            names += [alias.name for alias in node.names] if isinstance(node, ast.Import) else []
            offenders += [
                f"{path.relative_to(ROOT)} imports {name}"
                for name in names
                if name.startswith("tests.") and name.rsplit(".", 1)[-1].startswith("test_")
            ]
    assert not offenders, offenders
