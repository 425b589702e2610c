"""The layers point down (read from the imports with ``ast``, so a lazy import inside a function
counts as much as one at the top):

* the SB3 extensions (``harness.sb3``) import nothing from ``envs`` and nothing else of
  ``harness``: they work on any Gymnasium env or VecEnv;
* ``envs`` imports nothing from ``harness``;
* each ``harness`` package imports only from its own layer and the layers below it, in the order
  sb3 < config (and processes, how a child Python is started) < factory < evaluation < results <
  training < commands, cli, bench; in particular
  configuration imports no training, evaluation or CLI module;
* only the factory (``harness/factory.py``) calls ``parallel_env``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Rank of each layer of ``harness``: a module may import from its own rank or a lower one.
LAYERS = {
    "harness.sb3": 0,
    "harness.config": 1,
    "harness.processes": 1,
    "harness.factory": 2,
    "harness.evaluation": 3,
    "harness.results": 4,
    "harness.training": 5,
    "harness.commands": 6,
    "harness.cli": 6,
    "harness.bench": 6,
}


def modules(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> set[str]:
    """Every module ``path`` imports, absolute names (relative imports resolved)."""
    tree = ast.parse(path.read_text(), str(path))
    name = module_name(path) if path.is_relative_to(ROOT) else path.stem
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            found.add(base)
            # `from harness import training` imports a module, not a name
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return found


def layer(name: str) -> int | None:
    for prefix, rank in LAYERS.items():
        if name == prefix or name.startswith(prefix + "."):
            return rank
    return None


def test_every_harness_module_has_a_layer() -> None:
    for path in modules("harness"):
        name = module_name(path)
        assert name == "harness" or layer(name) is not None, f"{name} belongs to no layer"


@pytest.mark.parametrize("path", modules("harness/sb3"), ids=lambda p: p.name)
def test_the_sb3_extensions_import_no_env_and_no_upper_layer(path: Path) -> None:
    for name in imports(path):
        assert not (name == "envs" or name.startswith("envs.")), f"{path.name} imports {name}"
        if name.startswith("harness"):
            assert name.startswith("harness.sb3"), f"{path.name} imports {name}"


@pytest.mark.parametrize("path", modules("envs"), ids=lambda p: str(p.relative_to(ROOT)))
def test_the_env_imports_no_harness(path: Path) -> None:
    assert not [n for n in imports(path) if n.split(".")[0] == "harness"]


@pytest.mark.parametrize("path", modules("harness"), ids=lambda p: str(p.relative_to(ROOT)))
def test_layers_point_down(path: Path) -> None:
    own = layer(module_name(path))
    if own is None:  # harness/__init__.py: lazy re-exports of the SB3 classes
        assert {layer(n) for n in imports(path) if n.startswith("harness.")} <= {0}
        return
    for name in imports(path):
        other = layer(name)
        if other is not None:
            assert other <= own, f"{module_name(path)} (layer {own}) imports {name} ({other})"


def test_configuration_imports_no_training_evaluation_or_cli() -> None:
    banned = ("harness.training", "harness.evaluation", "harness.cli", "harness.commands")
    for path in modules("harness/config"):
        bad = [n for n in imports(path) if n.startswith(banned)]
        assert not bad, f"{path.name} imports {bad}"


def test_only_the_factory_calls_parallel_env() -> None:
    callers = []
    for path in [*modules("harness"), *modules("scripts"), *modules("experiments")]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call):
                func = node.func
                name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
                if name == "parallel_env":
                    callers.append(module_name(path))
    assert set(callers) == {"harness.factory"}


def test_the_checks_find_a_violation(tmp_path: Path) -> None:
    # The reader sees lazy imports too: the test above would catch one.
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from envs.coverage import env\n    return env\n")
    assert "envs.coverage" in imports(bad)
