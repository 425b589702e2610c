"""README is a short user guide and the reference lives in docs/ (the lab record in research/):
README's size and order, the CI blocks `.ci/run` reads, every relative link (research/'s too),
the configuration page against the schema, and the pages' lists of policies, planners, action
kinds and baselines against their registries."""

from __future__ import annotations

import dataclasses
import importlib
import re
import types
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
RESEARCH = ROOT / "research"
CONFIG_PAGE = DOCS / "configuration.md"
PAGES = [
    README,
    RESEARCH / "experiments" / "README.md",
    *sorted(DOCS.glob("*.md")),
    *sorted(RESEARCH.glob("*.md")),
]


# ---------------------------------------------------------------------- README
def test_readme_is_a_short_guide_with_the_commands_up_front() -> None:
    lines = README.read_text().splitlines()
    assert len(lines) <= 300, f"README.md has {len(lines)} lines; the reference goes to docs/"
    head = "\n".join(lines[:40])
    for command in ("harness run", "harness eval", "harness render", "harness compare"):
        assert command in head, f"{command!r} is not in README's first 40 lines"


def test_readme_keeps_the_ci_blocks() -> None:
    # `.ci/run` runs the first line of the fenced block after each marker.
    text = README.read_text()
    blocks = {
        "<!-- ci:setup -->": (
            'python3 -m venv .venv && . .venv/bin/activate && pip install -e ".[dev]" '
            "-c constraints.txt"
        ),
        "<!-- ci:test -->": ". .venv/bin/activate && pytest -n auto",
    }
    for marker, command in blocks.items():
        assert text.count(marker) == 1, marker
        assert f"{marker}\n```bash\n{command}\n```\n" in text, marker
    assert '`-m "not slow"`' in text  # the fast subset, named beside the full suite


# ---------------------------------------------------------------------- links
_FENCE = re.compile(r"^```.*?^```", re.M | re.S)
_CODE_SPAN = re.compile(r"`[^`\n]*`")
_LINK = re.compile(r"!?\[[^\]\n]*\]\(([^)\s]+)\)")


def relative_links(page: Path) -> list[str]:
    """The link targets of ``page`` that are neither URLs nor in-page anchors (code left out)."""
    text = _CODE_SPAN.sub("", _FENCE.sub("", page.read_text()))
    targets = (m.group(1) for m in _LINK.finditer(text))
    return [t for t in targets if not re.match(r"[a-z][a-z0-9+.-]*:|#", t)]


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = heading.strip().lower().replace("`", "")
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = _FENCE.sub("", page.read_text())
    return {slug(h) for h in re.findall(r"^#{1,6} (.+)$", text, re.M)}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_point_to_existing_files(page: Path) -> None:
    broken = []
    for target in relative_links(page):
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path).resolve()
        if not resolved.exists():
            broken.append(target)
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            broken.append(f"{target} (no such heading)")
    assert not broken, f"{page.name}: {broken}"


def test_in_page_anchors_exist() -> None:
    for page in PAGES:
        text = _CODE_SPAN.sub("", _FENCE.sub("", page.read_text()))
        own = anchors(page)
        missing = [a for a in re.findall(r"\]\(#([^)\s]+)\)", text) if a not in own]
        assert not missing, f"{page.name}: {missing}"


# ---------------------------------------------------------------------- configuration page
#: What a documented key starts with; rows under "Old configs" name old keys and are left out.
KEY_PREFIXES = ("env.", "vec.", "algo.", "phases[].", "eval.", "checkpoint.", "prior.")
TOP_LEVEL = ("name", "seed", "env", "prior")  # env: the env source (a union); prior: optional
#: Options of the env that a config writes as a mapping: documented as sub-option rows and
#: checked against the env's options classes (not the pydantic schema, which takes a mapping).
SUB_OPTIONS = {
    "env.observation.teammap.": (
        "envs.coverage.observations",
        "TeamMap",
        {"crop", "global_size", "ego_size", "ego_block"},
    ),
    "env.frontier.": ("envs.coverage.frontier", "FrontierOptions", {"action", "planner"}),
}


def documented_keys() -> list[str]:
    """The backticked keys in the first column of the configuration page's tables, in order."""
    keys, section = [], ""
    for line in CONFIG_PAGE.read_text().splitlines():
        if line.startswith("## "):
            section = line[3:].strip()
        if section.startswith("Old configs") or not line.startswith("|"):
            continue
        first = line.strip("|").split("|")[0].strip()
        match = re.fullmatch(r"`([^`]+)`", first)
        if match and (match[1] in TOP_LEVEL or match[1].startswith(KEY_PREFIXES)):
            keys.append(match[1])
    return keys


def _unwrap(tp: object) -> object:
    while typing.get_origin(tp) is typing.Annotated:
        tp = typing.get_args(tp)[0]
    return tp


def _is_model(tp: object) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def schema_keys(model: type[BaseModel], prefix: str = "") -> set[str]:
    """Every key of ``model`` as a dotted path: nested sections are recursed into (a list of
    sections as ``key[].``), an optional section is the key itself and its keys, a union of
    sections (``env``: the coverage env's or a PettingZoo source's) is the key itself and each
    section's keys, and anything else (plain values, dicts, unions such as ``env.map``) is the
    key itself."""
    keys: set[str] = set()
    for name, field in model.model_fields.items():
        key = prefix + name
        tp = _unwrap(field.annotation)
        origin, args = typing.get_origin(tp), [_unwrap(a) for a in typing.get_args(tp)]
        if _is_model(tp):
            keys |= schema_keys(tp, key + ".")
        elif origin is list and args and _is_model(args[0]):
            keys |= schema_keys(args[0], key + "[].")
        elif origin in (typing.Union, types.UnionType):
            models = [a for a in args if _is_model(a)]
            rest = [a for a in args if not _is_model(a)]
            keys.add(key)
            if len(models) == 1 and rest == [type(None)]:  # an optional section
                keys |= schema_keys(models[0], key + ".")
            elif len(models) > 1 and not rest:  # sections of several kinds (the env sources)
                for section in models:
                    keys |= schema_keys(section, key + ".")
        else:
            keys.add(key)
    return keys


def option_names(module: str, cls: str, fallback: set[str]) -> set[str]:
    """The option names of the env's options class ``module.cls`` (a dataclass or a pydantic
    model), or ``fallback`` while that class does not exist."""
    try:
        options = getattr(importlib.import_module(module), cls)
    except (ImportError, AttributeError):
        return fallback
    if dataclasses.is_dataclass(options):  # (a field marked config: False is an object)
        return {f.name for f in dataclasses.fields(options) if f.metadata.get("config", True)}
    if _is_model(options):
        return set(options.model_fields)
    return fallback


def test_configuration_page_lists_each_key_once() -> None:
    keys = documented_keys()
    assert keys, "no key rows found in docs/configuration.md"
    assert len(keys) == len(set(keys)), sorted(k for k in keys if keys.count(k) > 1)


def test_configuration_page_lists_exactly_the_schema_keys() -> None:
    from harness.config import ExperimentConfig

    def main(keys: set[str]) -> set[str]:
        return {k for k in keys if not k.startswith(tuple(SUB_OPTIONS))}

    schema = main(schema_keys(ExperimentConfig))
    page = main(set(documented_keys()))
    assert not schema - page, f"not in docs/configuration.md: {sorted(schema - page)}"
    assert not page - schema, f"only in docs/configuration.md: {sorted(page - schema)}"


@pytest.mark.parametrize("prefix", list(SUB_OPTIONS))
def test_configuration_page_lists_exactly_the_env_options(prefix: str) -> None:
    module, cls, fallback = SUB_OPTIONS[prefix]
    keys = documented_keys()
    documented = {k[len(prefix) :] for k in keys if k.startswith(prefix)}
    assert documented == option_names(module, cls, fallback)
    assert prefix.split(".")[0] + "." + prefix.split(".")[1] in keys  # the key itself, too


# ---------------------------------------------------------------------- registries
def policy_table(page: Path) -> dict[str, str]:
    """The ``--policy`` table of ``page``: each baseline's name and its last column (what it
    runs on), in the page's order."""
    rows, inside = {}, False
    for line in page.read_text().splitlines():
        if line.startswith("| `--policy` |"):
            inside = True
        elif inside and not line.startswith("|"):
            break
        elif inside and not line.startswith("|---"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows[cells[0].strip("`")] = cells[-1]
    return rows


def backticked_names(text: str) -> list[str]:
    """The backticked lower-case names of ``text`` (``frontier_pocket``, ``order``), in order."""
    return re.findall(r"`([a-z][a-z_]*)`", text)


def config_row(key: str) -> str:
    """The values column of ``key``'s row on the configuration page."""
    for line in CONFIG_PAGE.read_text().splitlines():
        if line.startswith(f"| `{key}` |"):
            return line.strip("|").split("|")[2]
    raise AssertionError(f"no row for {key} in docs/configuration.md")


def test_evaluation_page_lists_every_baseline_and_where_it_runs() -> None:
    from harness.evaluation.baselines import BASELINES

    table = policy_table(DOCS / "evaluation.md")
    assert list(table) == list(BASELINES)
    for name, runs_on in table.items():
        needs = "`env.frontier.action" in runs_on
        assert needs == BASELINES[name].needs_action, f"{name}: {runs_on!r}"
        assert ("{goal: ...}" in runs_on) == BASELINES[name].holds_goals, f"{name}: {runs_on!r}"
        anywhere = "any config, a pettingzoo env's too" if BASELINES[name].any_env else "any config"
        assert needs or runs_on == anywhere, f"{name}: {runs_on!r}"


def test_planners_page_lists_the_planners_baselines_and_the_action_kinds() -> None:
    from envs.coverage.frontier import ACTIONS, PLANNERS
    from harness.evaluation.baselines import BASELINES

    text = (DOCS / "planners.md").read_text()
    table = policy_table(DOCS / "planners.md")
    playing = [e.baseline for e in PLANNERS.values()]
    playing += [name for name, b in BASELINES.items() if b.needs_action]
    assert list(table) == playing
    for name, needs in table.items():
        assert ("`env.frontier.action" in needs) == BASELINES[name].needs_action, name
    listed = re.search(r"\(the planners: ([^)]*)\)", text)
    assert listed and sorted(backticked_names(listed[1])) == sorted(PLANNERS)
    listed = re.search(r"\(the planner-backed action kinds: ([^)]*)\)", text)
    assert listed and backticked_names(listed[1]) == list(ACTIONS)


def test_readme_names_only_real_baselines() -> None:
    # README's eval row names some baselines and points to docs/evaluation.md for all of them.
    from harness.evaluation.baselines import BASELINES

    (row,) = [r for r in README.read_text().splitlines() if r.startswith("| `harness eval ")]
    named = re.search(r"a baseline \(([^)]*)\)", row)
    assert named and "..." in named[1]
    assert set(backticked_names(named[1])) <= set(BASELINES)
    assert "docs/evaluation.md" in row


def test_configuration_page_lists_the_registries_choices() -> None:
    from envs.coverage.frontier import ACTIONS, PLANNERS
    from harness.sb3.registry import POLICIES

    assert set(re.findall(r"`(\w+Policy)`", config_row("algo.policy"))) == set(POLICIES)
    planners = set(backticked_names(config_row("env.frontier.planner"))) - {"null"}
    assert planners == set(PLANNERS)
    actions = config_row("env.frontier.action")
    for name in ACTIONS:
        assert f"`{name}`" in actions or f"`{{{name}:" in actions, name
