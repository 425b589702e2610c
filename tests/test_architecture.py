"""The layers point down (read from the imports with ``ast``, so a lazy import inside a function
counts as much as one at the top):

* the SB3 extensions (``harness.sb3``) import nothing from ``envs`` and nothing else of
  ``harness``: they work on any Gymnasium env or VecEnv;
* ``envs`` imports nothing from ``harness``;
* each ``harness`` package imports only from its own layer and the layers below it, in the order
  sb3 < config (and processes, how a child Python is started) < factory < evaluation < results <
  training < commands, cli, bench; in particular
  configuration imports no training, evaluation or CLI module;
* no import circle among ``harness`` modules (lazy imports counted): a module never reaches
  itself through its imports;
* only the factory (``harness/factory.py``) calls ``parallel_env``;
* no module of ``harness``, ``envs``, ``scripts`` or ``tests`` imports the research record
  (``research``, ``experiments``): research scripts may use the product, never the reverse;
* a run folder's file names (``config.yaml``, ``checkpoints``, ``state.json``, ...) are spelled
  only by their owner, ``harness/results/rundir.py`` (``RunDir``, ``CheckpointDir``): no other
  ``harness`` module has a string literal that is such a name or a path through one (prose that
  mentions a file, in a message or a docstring, is no spelling of its path);
* a run's state (new, stopped before its first checkpoint, resumable, finished) is decided only
  by ``harness/training/state.py``: only it (and ``harness/training/train.py``, which loads the
  checkpoint a resume continues from) reads a run's checkpoints to tell where it stands, and
  outside the training package nothing of ``harness/training/checkpoints.py`` but its errors is
  used; what a resume does with that state, and which trainer (policy or prior) a config gets,
  is ``harness/training/start.py``'s: the CLI reads no state and picks no trainer;
* the rollout teacher (``envs/coverage/teacher.py``), which sees the true map, is for training
  only: no code of evaluation (``harness/evaluation``, ``harness/commands.py``, the CLI's
  ``eval``, ``compare`` and ``render``, and the env they play) reaches it through its imports.
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
    # A module of its own rank, listed before its package (the first prefix that matches
    # counts): the run folder's names, which every layer reads, sit with the config; the map
    # prior's network sits with the factory, which hands a prior to the env (env.prior).
    "harness.results.rundir": 1,
    "harness.prior.coding": 2,
    "harness.prior.model": 2,
    "harness.factory": 2,
    "harness.tasks": 2,
    "harness.evaluation": 3,
    "harness.results": 4,
    "harness.prior": 4,
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
    return imports_in(tree, package)


def imports_in(tree: ast.AST, package: str) -> set[str]:
    """Every module the code of ``tree`` (a module's, or one function's) imports, absolute
    names (relative imports resolved against ``package``)."""
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


def runtime_imports(path: Path) -> set[str]:
    """The modules that running ``path``'s code imports (lazy imports included, those under
    ``if TYPE_CHECKING:`` left out: they never run). ``from package import module`` imports
    ``module`` (the package is its parent, imported already); ``from module import name``
    imports ``module``."""
    tree = ast.parse(path.read_text(), str(path))
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            names = imports_in(node, package)
            if isinstance(node, ast.ImportFrom):
                base = min(names, key=len)
                submodules = {n for n in names - {base} if module_path(n) is not None}
                found.update(submodules if len(submodules) == len(node.names) else names)
            else:
                found.update(names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def import_graph(paths: list[Path]) -> dict[str, set[str]]:
    """Each module of ``paths`` and the modules among them it imports when it runs
    (:func:`runtime_imports`)."""
    names = {module_name(path): path for path in paths}
    return {
        name: {n for n in runtime_imports(path) if n in names and n != name}
        for name, path in names.items()
    }


def import_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of ``graph`` (``[a, b, a]``: ``a`` imports ``b``, which imports
    ``a``), or ``None``."""
    done: set[str] = set()
    for start in sorted(graph):
        path: list[str] = []
        on_path: set[str] = set()
        stack = [(start, iter(sorted(graph[start])))]
        if start in done:
            continue
        path.append(start)
        on_path.add(start)
        while stack:
            node, children = stack[-1]
            child = next(children, None)
            if child is None:
                stack.pop()
                path.pop()
                on_path.discard(node)
                done.add(node)
            elif child in on_path:
                return [*path[path.index(child) :], child]
            elif child not in done:
                stack.append((child, iter(sorted(graph[child]))))
                path.append(child)
                on_path.add(child)
    return None


def test_no_import_circle_among_harness_modules() -> None:
    cycle = import_cycle(import_graph(modules("harness")))
    assert cycle is None, f"an import circle: {' -> '.join(cycle or [])}"


def test_the_circle_check_finds_a_lazy_circle(tmp_path: Path) -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert import_cycle(graph) == ["a", "b", "c", "a"]
    assert import_cycle({"a": {"b"}, "b": set(), "c": {"b"}}) is None
    # A lazy import inside a function is an edge too.
    lazy = tmp_path / "lazy.py"
    lazy.write_text("def f():\n    from harness.evaluation import episodes\n")
    assert "harness.evaluation.episodes" in imports(lazy)


def test_configuration_imports_no_training_evaluation_or_cli() -> None:
    banned = ("harness.training", "harness.evaluation", "harness.cli", "harness.commands")
    for path in modules("harness/config"):
        bad = [n for n in imports(path) if n.startswith(banned)]
        assert not bad, f"{path.name} imports {bad}"


def test_only_the_factory_calls_parallel_env() -> None:
    callers = []
    for path in [*modules("harness"), *modules("scripts")]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call):
                func = node.func
                name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
                if name == "parallel_env":
                    callers.append(module_name(path))
    assert set(callers) == {"harness.factory"}


#: The lab record's packages, which the product and its tests never import.
RESEARCH = ("research", "experiments")


@pytest.mark.parametrize(
    "path",
    [*modules("harness"), *modules("envs"), *modules("scripts"), *modules("tests")],
    ids=lambda p: str(p.relative_to(ROOT)),
)
def test_nothing_imports_the_research_record(path: Path) -> None:
    bad = sorted(n for n in imports(path) if n.split(".")[0] in RESEARCH)
    assert not bad, f"{module_name(path)} imports the research record: {bad}"


def test_the_research_scripts_live_in_the_research_record() -> None:
    assert not (ROOT / "experiments").exists() and (ROOT / "research" / "experiments").is_dir()


def test_the_checks_find_a_violation(tmp_path: Path) -> None:
    # The reader sees lazy imports too: the test above would catch one.
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from envs.coverage import env\n    return env\n")
    assert "envs.coverage" in imports(bad)
    bad.write_text("def f():\n    from research.experiments import goal_oracle\n")
    assert "research.experiments" in imports(bad)


# ----------------------------------------------------------------- run-file names, one owner
#: The module that spells a run folder's file names.
RUN_FILES_OWNER = "harness.results.rundir"


def run_file_names() -> frozenset[str]:
    """Every file and folder name of a run folder and of a checkpoint, read from their owner's
    properties (so a name added there is checked here too)."""
    from harness.results import rundir

    names = {rundir.RunDir(Path()).progress_csv().name, *rundir.REFERENCE_FILES}
    for cls in (rundir.RunDir, rundir.CheckpointDir):
        blank = cls(Path())
        for attr, value in vars(cls).items():
            path = getattr(blank, attr) if isinstance(value, property) else None
            if isinstance(path, Path):
                names.add(path.name)
    return frozenset(names)


def docstring_nodes(tree: ast.AST) -> set[int]:
    """The string statements of ``tree`` (docstrings, attribute docstrings), by ``id``."""
    return {
        id(node.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Expr)
        and isinstance(node.value, ast.Constant)
        and isinstance(node.value.value, str)
    }


def spelled_run_files(source: str, names: frozenset[str]) -> list[tuple[int, str]]:
    """``(line, literal)`` of each code string literal of ``source`` (the text parts of an
    f-string too) that is a name of ``names`` or a path through one (``"checkpoints/step-"``,
    ``f"{run}/config.yaml"``): one of its ``/``-separated parts is the name. Docstrings are left
    out, and so is prose that mentions a file (``"no config.yaml yet"``)."""
    tree = ast.parse(source)
    skip = docstring_nodes(tree)
    found = []
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Constant)
            and isinstance(node.value, str)
            and id(node) not in skip
            and names.intersection(node.value.split("/"))
        ):
            found.append((node.lineno, node.value))
    return found


def test_the_run_file_names_are_read_from_their_owner() -> None:
    names = run_file_names()
    # The names every rule of this file relies on (a renamed property must not empty the set).
    assert {"config.yaml", "checkpoints", "state.json", "model.zip", ".lock", "tb"} <= names


@pytest.mark.parametrize(
    "path",
    [*modules("harness"), *modules("scripts")],
    ids=lambda p: str(p.relative_to(ROOT)),
)
def test_only_the_run_dir_spells_run_file_names(path: Path) -> None:
    if module_name(path) == RUN_FILES_OWNER:
        return
    spelled = spelled_run_files(path.read_text(), run_file_names())
    assert not spelled, f"{module_name(path)} spells run-file names (use RunDir): {spelled}"


def test_the_run_file_check_finds_a_spelling() -> None:
    snippet = (
        '"""A module about config.yaml."""\n'
        "START = frozenset({'.lock', 'config.yaml'})\n"
        "def newest(run, step):\n"
        '    """The newest checkpoints/ folder."""\n'
        '    print(f"{run}: no config.yaml yet")\n'
        '    return f"{run}/checkpoints/step-{step}"\n'
    )
    spelled = spelled_run_files(snippet, run_file_names())
    assert spelled == [(2, ".lock"), (2, "config.yaml"), (6, "/checkpoints/step-")]


# ------------------------------------------------------------------ run state, one owner
#: The module that decides a run's state.
RUN_STATE_OWNER = "harness.training.state"
#: What tells where a run stands: its complete checkpoints and the newest one's ``state.json``.
CHECKPOINT_READERS = frozenset({"complete_checkpoints", "latest_checkpoint", "read_state"})
#: Who may read them: the owner, and the training that loads the checkpoint a resume continues
#: from (and the module that writes them).
MAY_READ_CHECKPOINTS = frozenset(
    {
        RUN_STATE_OWNER,
        "harness.training.train",
        "harness.training.prior",
        "harness.training.checkpoints",
    }
)
#: What of the checkpoints module the layers above training may use: its errors.
CHECKPOINT_ERRORS = frozenset({"CheckpointError", "ConfigChangedError"})


def checkpoint_uses(path: Path) -> set[str]:
    """The names ``path`` takes from ``harness.training.checkpoints`` (``*``: the module itself,
    whose every name it may then use), lazy imports included."""
    checkpoints = "harness.training.checkpoints"
    used: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module == checkpoints:
            used.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module == "harness.training":
            used.update("*" for alias in node.names if alias.name == "checkpoints")
        elif isinstance(node, ast.Import):
            used.update("*" for alias in node.names if alias.name == checkpoints)
    return used


def state_rule_breaches(path: Path) -> list[str]:
    """What ``path`` uses of the checkpoints that the run-state owner alone may use."""
    name = module_name(path) if path.is_relative_to(ROOT) else path.stem
    used = checkpoint_uses(path)
    bad = sorted(used & CHECKPOINT_READERS) if name not in MAY_READ_CHECKPOINTS else []
    if not name.startswith("harness.training."):
        bad += sorted(used - CHECKPOINT_ERRORS - CHECKPOINT_READERS)
    return bad


@pytest.mark.parametrize("path", modules("harness"), ids=lambda p: str(p.relative_to(ROOT)))
def test_only_the_state_owner_decides_a_runs_state(path: Path) -> None:
    bad = state_rule_breaches(path)
    assert not bad, f"{module_name(path)} uses {bad} (ask {RUN_STATE_OWNER}.run_state)"


@pytest.mark.parametrize("path", modules("harness"), ids=lambda p: str(p.relative_to(ROOT)))
def test_whether_a_folder_is_a_run_is_asked_of_the_run_dir(path: Path) -> None:
    # RunDir.is_run says it (its config.yaml); nobody tests that file for it on their own.
    if module_name(path) == RUN_FILES_OWNER:
        return
    text = path.read_text()
    assert ".config.is_file()" not in text, f"{module_name(path)}: ask RunDir(...).is_run"


def test_the_run_state_check_finds_a_breach(tmp_path: Path) -> None:
    reader = tmp_path / "reader.py"
    reader.write_text(
        "def finished(run):\n"
        "    from harness.training.checkpoints import complete_checkpoints, read_state\n"
        "    return read_state(complete_checkpoints(run.checkpoints)[-1]).finished\n"
    )
    assert state_rule_breaches(reader) == ["complete_checkpoints", "read_state"]
    asker = tmp_path / "asker.py"
    asker.write_text(
        "from harness.training.checkpoints import CheckpointError, check_config\n"
        "from harness.training.state import run_state\n"
    )
    assert state_rule_breaches(asker) == ["check_config"]


#: The module that decides what ``harness run`` does with a run folder.
START = "harness.training.start"
#: What decides what a run's command does with its state, and which trainer a config gets: the
#: training layer's (:data:`START`), never the command line's.
RUN_DECISIONS = frozenset(
    {
        "RunState",
        "never_started",
        "finished",
        "NO_CHECKPOINT",
        "RESUMABLE",
        "FINISHED",
        "check_resume_config",
        "check_training_device",
        "train_prior",
        "train",
        "prior",
    }
)


def run_decisions(path: Path) -> list[str]:
    """The names and attributes of :data:`RUN_DECISIONS` that ``path``'s code uses (a run's
    state read, compared or acted on; a trainer picked), each once, sorted."""
    used: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Name):
            used.add(node.id)
        elif isinstance(node, ast.Attribute):
            used.add(node.attr)
        elif isinstance(node, ast.alias):
            used.add(node.asname or node.name)
    return sorted(used & RUN_DECISIONS)


def test_the_cli_decides_no_run_state_and_picks_no_trainer() -> None:
    # harness.training.start says what a resume does (and the line to print) and trains a
    # config, a policy or a prior; the command line parses, calls and prints.
    bad = run_decisions(ROOT / "harness" / "cli.py")
    assert not bad, f"harness.cli decides a run's state or its trainer ({bad}): see {START}"


def test_the_run_decision_check_finds_one(tmp_path: Path) -> None:
    cli = tmp_path / "cli.py"
    cli.write_text(
        "from harness.training.state import RunState, run_state\n"
        "def resume(run, config):\n"
        "    status = run_state(run)\n"
        "    if status.finished:\n"
        "        return 0\n"
        "    if config.prior is not None:\n"
        "        from harness.training.prior import train_prior as train\n"
        "    train(config, run)\n"
    )
    assert run_decisions(cli) == ["RunState", "finished", "prior", "train"]


# ------------------------------------------------------------------ the teacher, training only
#: The rollout teacher: it chooses with the true map, so it may label training's states but
#: must never choose in evaluation.
TEACHER = "envs.coverage.teacher"
#: The CLI's commands that evaluate (functions of ``harness/cli.py``).
EVALUATING_COMMANDS = ("cmd_eval", "cmd_compare", "cmd_render")


def module_path(name: str) -> Path | None:
    """The file of module ``name`` of this repository (``None``: no such module, e.g. a name
    imported from one, or a third-party module)."""
    base = ROOT.joinpath(*name.split("."))
    for path in (base / "__init__.py", base.with_suffix(".py")):
        if path.is_file():
            return path
    return None


def reached(names: set[str]) -> set[str]:
    """``names`` and everything they import, transitively through this repository's modules
    (lazy imports included): what their code can reach."""
    seen: set[str] = set()
    todo = list(names)
    while todo:
        name = todo.pop()
        if name not in seen:
            seen.add(name)
            path = module_path(name)
            if path is not None:
                todo.extend(imports(path))
    return seen


def command_imports(path: Path, commands: tuple[str, ...]) -> set[str]:
    """What the functions ``commands`` of the module at ``path`` import: the imports in their
    bodies and in the bodies of the module's functions they call (transitively), and the
    modules whose module-level imports give the names they use (``from a.b import c``: ``a.b``
    and ``a.b.c``). The module's other functions (a CLI's training commands) are left out."""
    tree = ast.parse(path.read_text(), str(path))
    package = module_name(path).rpartition(".")[0] if path.is_relative_to(ROOT) else ""
    functions = {node.name: node for node in tree.body if isinstance(node, ast.FunctionDef)}
    given: dict[str, set[str]] = {}  # a module-level imported name -> where it comes from
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for alias in node.names:
                given[alias.asname or alias.name] = {node.module, f"{node.module}.{alias.name}"}
        elif isinstance(node, ast.Import):
            for alias in node.names:
                given[alias.asname or alias.name.split(".")[0]] = {alias.name}
    found: set[str] = set()
    todo, done = list(commands), set()
    while todo:
        name = todo.pop()
        if name in done:
            continue
        done.add(name)
        found |= imports_in(functions[name], package)
        for node in ast.walk(functions[name]):
            if isinstance(node, ast.Name) and node.id in functions:
                todo.append(node.id)
            elif isinstance(node, ast.Name) and node.id in given:
                found |= given[node.id]
    return found


def evaluation_code() -> set[str]:
    """The modules and names the evaluation code starts from (see the module docstring)."""
    starts = {module_name(path) for path in modules("harness/evaluation")}
    starts |= {"harness.commands", "envs.coverage.env", "envs.coverage.core"}
    return starts | command_imports(ROOT / "harness" / "cli.py", EVALUATING_COMMANDS)


def test_evaluation_never_reaches_the_teacher() -> None:
    code = reached(evaluation_code())
    # The reader follows the imports through (the env's planners, the commands' evaluation).
    assert {"harness.commands", "harness.evaluation.episodes", "envs.coverage.planners"} <= code
    bad = sorted(n for n in code if n == TEACHER or n.startswith(TEACHER + "."))
    assert not bad, f"evaluation code reaches the rollout teacher ({bad}): it is for training only"


def test_the_teacher_check_finds_a_way_in(tmp_path: Path) -> None:
    cli = tmp_path / "cli.py"
    cli.write_text(
        "from harness.commands import evaluate\n"
        "from envs.coverage.teacher import shortest_walk\n"
        "def cmd_run(args):\n"
        "    from envs.coverage.teacher import RolloutTeacher\n"
        "    return shortest_walk\n"
        "def _helper():\n"
        "    from envs.coverage import teacher\n"
        "def cmd_eval(args):\n"
        "    return evaluate(_helper())\n"
        "def cmd_compare(args):\n"
        "    from harness.training.teacher import TeacherLabeller\n"
        "    return TeacherLabeller\n"
    )
    assert command_imports(cli, ("cmd_run",)) >= {TEACHER, "envs.coverage.teacher.shortest_walk"}
    found = command_imports(cli, ("cmd_eval",))
    assert {"harness.commands", "harness.commands.evaluate", TEACHER} <= found
    assert "envs.coverage.teacher.shortest_walk" not in found  # used by cmd_run alone
    # An import in a module the code imports counts too (the training labeller imports it).
    found = command_imports(cli, ("cmd_compare",))
    assert TEACHER not in found and TEACHER in reached(found)
