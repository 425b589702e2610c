"""Loading a config: YAML (safe, no duplicate keys, bounded), ``--set key.path=value``
overrides, the migration of old layouts, and validation against the schema
(:mod:`harness.config.schema`), with one-line errors."""

from __future__ import annotations

import contextlib
import copy
import difflib
import re
import stat
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, NoReturn, get_args, get_origin

import yaml
from pydantic import BaseModel, ValidationError

from harness.config.maps import SHA256
from harness.config.migrate import migrate
from harness.config.schema import (
    ENV_SECTIONS,
    ENV_SOURCES,
    MAX_CONFIG_BYTES,
    ConfigError,
    ExperimentConfig,
)


# ---------------------------------------------------------------------- loading
def _format_error(source: str, err: ValidationError) -> str:
    first = err.errors()[0]
    loc = ".".join(str(p) for p in _config_loc(first["loc"])) or "(top level)"
    msg = first["msg"].removeprefix("Value error, ")
    if first["type"] == "extra_forbidden":
        guess = _closest_key(first["loc"])
        msg += f" (did you mean {guess}?)" if guess else ""
    more = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
    return f"{source}: {loc}: {msg}{more}"


def _config_loc(loc: Sequence[Any]) -> tuple[Any, ...]:
    """A validation error's location as a config writes it: without the ``env`` section's
    source tag that pydantic puts after ``env`` (``env.coverage.height`` is ``env.height``)."""
    if len(loc) >= 2 and loc[0] == "env" and loc[1] in ENV_SOURCES:
        return (loc[0], *loc[2:])
    return tuple(loc)


def _closest_key(loc: tuple[Any, ...]) -> str | None:
    """The key of the schema's section at ``loc[:-1]`` (a validation error's location, with the
    env source's tag) nearest to the unknown ``loc[-1]`` (difflib), dotted as a config writes
    it; ``None`` when nothing is near."""
    model: Any = ExperimentConfig
    for i, part in enumerate(loc[:-1]):
        if isinstance(part, int):
            continue  # an item of a list section (phases.0)
        if i == 1 and loc[0] == "env" and part in ENV_SECTIONS:
            model = ENV_SECTIONS[part]  # the env section of that source
            continue
        nested, _ = _field_model(model, str(part))
        if nested is None:
            return None
        model = nested
    names = list(getattr(model, "model_fields", {}))
    close = difflib.get_close_matches(str(loc[-1]), names, n=1, cutoff=0.6)
    if not close:
        return None
    path = [str(p) for p in _config_loc(loc)[:-1]] + close
    return f"`{'.'.join(path)}`"


#: An unquoted number in YAML 1.1's blind spot (``1e-4``, ``5E3``): ``--set`` reads it as one.
_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)[eE][+-]?\d+")


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split ``a.b.c=value`` into a key path and a YAML-parsed value.

    Raises:
        ConfigError: when there is no ``=`` or no key.
    """
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"--set {text!r}: expected key.path=value")
    try:
        # A config file's loader: a key twice inside the value is refused, as in a file.
        value = yaml.load(raw, Loader=_UniqueKeyLoader) if raw.strip() else None
    except YamlAliasError as exc:
        raise ConfigError(f"--set {text[:40]!r}: {exc}") from None
    except yaml.constructor.ConstructorError as exc:  # a key twice, a leading zero, a !tag
        raise ConfigError(f"--set {text[:40]!r}: {exc.problem}") from None
    except RecursionError:
        raise ConfigError(f"--set {text[:40]!r}...: value nested too deeply") from None
    except ValueError as exc:  # e.g. an integer of more digits than Python converts
        raise ConfigError(f"--set {text[:40]!r}: {str(exc).split(';')[0][:120]}") from None
    except yaml.YAMLError:
        value = raw  # not YAML: keep the text; the schema decides whether a string fits
    if isinstance(value, str) and _NUMBER.fullmatch(raw.strip()):
        # YAML 1.1 reads "1e-4" (no dot) as text; on the command line it means a number. A
        # quoted value ("2024") stays the text it was written as.
        with contextlib.suppress(ValueError):
            value = float(value)
    return key.strip().split("."), value


def apply_override(data: dict[str, Any], path: Sequence[str], value: Any, text: str) -> None:
    """Set ``value`` at ``path`` in nested dicts/lists. List items are picked by index or, for
    lists of named items such as ``phases``, by name (``phases.optimizing.timesteps=...``).

    A mapping given for a *section* of the schema (``env={n_agents: 3}``, ``phases.0={...}``,
    ``env.rewards={...}``) is merged into it, key by key and down into its own sections, so the
    keys it leaves out keep their values (the one rule for ``--set`` and a sweep's space-file
    values). Any other value replaces what is there: a list, and a free-form mapping such as
    ``env.map`` or ``env.observation`` (two map kinds would not make one map)."""
    node: Any = data
    for i, key in enumerate(path):
        last = i == len(path) - 1
        where = ".".join(path[: i + 1])
        if isinstance(node, list):
            idx = _list_index(node, key)
            if idx is None:
                raise ConfigError(f"--set {text}: no item {key!r} at {where}")
            if last:
                node[idx] = _merged(node[idx], value, _schema_section(path))
            else:
                node = node[idx]
        elif isinstance(node, dict):
            if last:
                node[key] = _merged(node.get(key), value, _schema_section(path))
            else:
                node = node.setdefault(key, {})
        else:
            raise ConfigError(f"--set {text}: {'.'.join(path[:i])} is not a section")


def _merged(old: Any, value: Any, section: type[BaseModel] | None) -> Any:
    """``value`` put in the place of ``old``: merged into it when both are mappings and the place
    is the schema's ``section`` (recursively, section by section), else ``value`` itself."""
    if section is None or not isinstance(old, dict) or not isinstance(value, dict):
        return value
    merged = dict(old)
    for key, item in value.items():
        sub, is_list = _field_model(section, str(key))
        merged[key] = _merged(merged.get(key), item, None if is_list else sub)
    return merged


def _field_model(model: type[BaseModel], key: str) -> tuple[type[BaseModel] | None, bool]:
    """The section (a pydantic model) that ``model``'s field ``key`` holds, or ``None`` (a value,
    a free-form mapping, no such field), and whether the field is a list of them."""
    field = model.model_fields.get(key)
    if field is None:
        return None, False
    annotation = field.annotation
    is_list = get_origin(annotation) is list
    candidates = get_args(annotation) if is_list else (annotation, *get_args(annotation))
    # A tagged union's members (the env sources) are Annotated: their first argument is the
    # model; the first model is the default source's (the coverage env's).
    candidates = tuple(get_args(c)[0] if get_origin(c) is Annotated else c for c in candidates)
    nested = [c for c in candidates if isinstance(c, type) and issubclass(c, BaseModel)]
    return (nested[0] if nested else None), is_list


def _schema_section(path: Sequence[str]) -> type[BaseModel] | None:
    """The schema's section at a ``--set`` key path (``env``, ``phases.0``, ``phases.initial``,
    ``env.rewards``), or ``None`` where the path names a value or a free-form mapping."""
    model: type[BaseModel] | None = ExperimentConfig
    in_list = False
    for key in path:
        if model is None:
            return None
        if in_list:  # the item of a list section, by index or name: the list's own model
            in_list = False
            continue
        model, in_list = _field_model(model, key)
    return None if in_list else model


def _list_index(items: list[Any], key: str) -> int | None:
    if key.lstrip("-").isdigit():
        idx = int(key)
        return idx if -len(items) <= idx < len(items) else None
    for idx, item in enumerate(items):
        if isinstance(item, dict) and item.get("name") == key:
            return idx
    return None


#: YAML's tags for a merge key (``<<: *base``), and for ``=`` which SafeLoader reads as text.
_MERGE, _VALUE, _STR = (f"tag:yaml.org,2002:{t}" for t in ("merge", "value", "str"))


#: Most nodes a YAML document may hold with its aliases expanded, when they add any: a config
#: has hundreds, and a file under the 1 MB cap without aliases at most about 500,000. Aliases
#: share one node, so 1 KB of them can stand for billions ("billion laughs"), which the
#: schema's checks and the run's config.yaml would write out one by one (gigabytes, a hang).
MAX_YAML_NODES = 100_000


class YamlAliasError(yaml.YAMLError):
    """A document whose aliases expand it past :data:`MAX_YAML_NODES` nodes, or an alias
    inside the node it names (a document without end)."""


class _BoundedLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that counts a document's nodes with its aliases expanded before
    building it (each node once, so the count takes as long as the written document) and refuses
    more than :data:`MAX_YAML_NODES` of them where aliases add nodes, and an alias that names a
    node it lies in."""

    def construct_document(self, node: yaml.Node) -> Any:
        written: dict[int, int] = {}  # id of a node -> its nodes, aliases expanded
        expanded = _expanded_size(node, written, set())
        if expanded > MAX_YAML_NODES and expanded > len(written):
            raise YamlAliasError(
                f"YAML aliases expand it to more than {MAX_YAML_NODES:,} values (it holds "
                f"{len(written):,}); write the values out, or use fewer aliases"
            )
        return super().construct_document(node)

    def construct_yaml_int(self, node: yaml.ScalarNode) -> int:
        """YAML 1.1's int, but not one written with a leading zero: ``010`` is octal 8 there (and
        ``09`` text), where anyone writing ``max_steps: 010`` means 10."""
        digits = str(node.value).replace("_", "").lstrip("+-")
        if len(digits) > 1 and digits[0] == "0" and digits[1].isdigit():
            raise yaml.constructor.ConstructorError(
                None,
                None,
                f"{node.value}: a number with a leading zero (YAML reads it as octal); write it "
                "without the zero",
                node.start_mark,
            )
        return super().construct_yaml_int(node)


_BoundedLoader.add_constructor("tag:yaml.org,2002:int", _BoundedLoader.construct_yaml_int)


def _expanded_size(node: yaml.Node, sizes: dict[int, int], open_: set[int]) -> int:
    """The number of nodes ``node`` stands for with its aliases expanded (an alias names the
    same node object), each node's counted once into ``sizes``; past :data:`MAX_YAML_NODES`
    the count stops growing, so a bomb is refused without adding its billions up.

    Raises:
        YamlAliasError: for a node inside itself (``&a [*a]``).
    """
    key = id(node)
    if key in sizes:
        return sizes[key]
    if key in open_:
        raise YamlAliasError("an alias names a node it lies inside (the document never ends)")
    open_.add(key)
    total = 1
    if isinstance(node, yaml.SequenceNode):
        children: list[yaml.Node] = list(node.value)
    elif isinstance(node, yaml.MappingNode):
        children = [part for pair in node.value for part in pair]
    else:
        children = []
    for child in children:
        total = min(total + _expanded_size(child, sizes, open_), MAX_YAML_NODES + 1)
    open_.discard(key)
    sizes[key] = total
    return total


class _UniqueKeyLoader(_BoundedLoader):
    """``yaml.SafeLoader`` that refuses a key given twice in one mapping (plain YAML keeps the
    last one silently, so a repeated ``learning_rate:`` would quietly win), and merges
    ``<<: *base`` as YAML defines it; aliases bounded (:class:`_BoundedLoader`)."""

    def flatten_mapping(self, node: yaml.MappingNode) -> None:
        """Check ``node``'s keys and merge its merge key into it (SafeLoader calls this for every
        mapping before building it, and here it is called for every mapping merged).

        The keys written in the mapping override the merged ones, so they are not duplicates;
        of ``<<: [*a, *b]`` the earlier mapping wins, as YAML defines (PyYAML's own merge lets
        the later one win unless the two keys happen to be one Python object). A key written
        twice, ``<<`` included, is refused. Afterwards ``node`` holds each key once and no
        merge key, so flattening it again (an alias merged elsewhere) changes nothing.
        """
        own: dict[Any, tuple[yaml.Node, yaml.Node]] = {}
        merged: dict[Any, tuple[yaml.Node, yaml.Node]] = {}
        merge_keys = 0
        for key_node, value_node in node.value:
            if key_node.tag == _MERGE:
                merge_keys += 1
                if merge_keys > 1:
                    self._duplicate("<<", key_node)
                sources = (
                    value_node.value if isinstance(value_node, yaml.SequenceNode) else [value_node]
                )
                for source in sources:
                    if not isinstance(source, yaml.MappingNode):
                        raise yaml.constructor.ConstructorError(
                            "while constructing a mapping",
                            node.start_mark,
                            f"expected a mapping or list of mappings for merging, but found "
                            f"{source.id}",
                            source.start_mark,
                        )
                    self.flatten_mapping(source)
                    for pair in source.value:
                        merged.setdefault(self._identity(pair[0]), pair)  # the first one wins
                continue
            if key_node.tag == _VALUE:  # as SafeLoader does
                key_node.tag = _STR
            key = self._identity(key_node)
            if key in own:
                self._duplicate(self.construct_object(key_node), key_node)
            own[key] = (key_node, value_node)
        node.value = [pair for key, pair in merged.items() if key not in own] + [*own.values()]

    def _identity(self, key_node: yaml.Node) -> Any:
        """The key a key node makes; an unhashable one stands for itself (SafeLoader refuses it
        when the mapping is built, with its own message)."""
        key = self.construct_object(key_node)
        try:
            hash(key)
        except TypeError:
            return ("unhashable", id(key_node))
        return key

    @staticmethod
    def _duplicate(key: Any, key_node: yaml.Node) -> NoReturn:
        raise yaml.constructor.ConstructorError(
            None, None, f"duplicate key {key!r}", key_node.start_mark
        )


def parse_yaml(text: str, source: str) -> Any:
    """Parse config YAML safely: no Python objects, no duplicate keys, bounded nesting and
    aliases (:data:`MAX_YAML_NODES`).

    Raises:
        ConfigError: naming ``source`` and, where known, the line and column.
    """
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)
    except YamlAliasError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{source}: {where}invalid YAML ({problem})") from None
    except RecursionError:
        raise ConfigError(f"{source}: invalid YAML (nested too deeply)") from None
    except ValueError as exc:  # e.g. an integer of more digits than Python converts
        raise ConfigError(f"{source}: invalid YAML ({str(exc).split(';')[0][:120]})") from None


def read_yaml_text(path: str | Path, what: str = "config file") -> str:
    """The text of a YAML file the user names (a config, a sweep's space file): a regular file
    of at most :data:`MAX_CONFIG_BYTES`, UTF-8.

    Raises:
        ConfigError: one line naming the file and ``what`` it should be.
    """
    path = Path(path)
    try:
        # A FIFO blocks the open until someone writes to it, /dev/zero never ends: only regular
        # files are read (as only regular files are map files).
        if not stat.S_ISREG(path.stat().st_mode):
            raise ConfigError(f"{path}: not a regular file (a {what} is YAML)")
        # Read at most one byte past the limit (the file may grow between stat and read).
        with path.open("rb") as f:
            data = f.read(MAX_CONFIG_BYTES + 1)
        if len(data) > MAX_CONFIG_BYTES:
            raise ConfigError(
                f"{path}: more than {MAX_CONFIG_BYTES:,} bytes is too large for a {what}"
            )
        return data.decode("utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: {what} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read {what} ({exc})") from None


def load_config(path: str | Path, overrides: Sequence[str] = ()) -> ExperimentConfig:
    """Read a YAML experiment file, apply ``--set`` overrides and validate.

    Raises:
        ConfigError: with one line naming the file (or the override) and the key.
    """
    path = Path(path)
    raw = parse_yaml(read_yaml_text(path), str(path))
    if raw is None:
        raise ConfigError(f"{path}: the config file is empty (see configs/ for examples)")
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections")
    return config_from_dict(raw, str(path), overrides)


def config_from_dict(
    raw: dict[str, Any], source: str = "<config>", overrides: Sequence[str] = ()
) -> ExperimentConfig:
    """Validate a config mapping, then apply overrides (on the validated, defaults-filled form so
    that ``--set phases.initial.timesteps=...`` works even when the file leaves phases out).
    A file of an older layout is migrated first (:func:`harness.config.migrate.migrate`).

    Overrides of the map keys (``env.map...``, ``env.test_maps``) are also applied before the
    first validation: the map they replace is never checked, so ``harness eval RUN --set
    env.map=random`` works when the run's map file is gone.

    A file that is invalid alone is validated once more with every override applied to it as
    written, so that ``--set algo.learning_starts=100`` repairs a file whose phases are shorter
    than the default warm-up: the file plus its ``--set``s is what is checked."""
    parsed: list[tuple[list[str], Any, str]] = []
    given: set[str] = set()
    for text in overrides:
        keys, value = parse_override(text)
        key = ".".join(keys)
        if key in given:
            raise ConfigError(f"--set {key} is given twice: give each key once")
        given.add(key)
        parsed.append((keys, value, text))
    early = [item for item in parsed if _replaces_a_map(item[0], item[1])]
    try:
        data = migrate(raw)
    except ValueError as err:  # a retired knob turned on
        raise ConfigError(f"{source}: {err}") from None
    first = source
    if early:
        for keys, value, text in early:
            _apply(data, keys, value, text)
        first = f"{source} with --set {' '.join(text for _, _, text in early)}"
    try:
        config = ExperimentConfig.model_validate(data)
    except ValueError as err:
        # The file plus its --sets is what is checked: a file invalid alone (a 600-transition
        # phase under the default learning_starts) may be repaired by an override.
        config = _validated_with_overrides(data, parsed, source)
        if config is None:
            if not isinstance(err, ValidationError):
                raise ConfigError(f"{first}: {err}") from None
            raise ConfigError(_format_error(first, err)) from None
    if overrides:
        data = config.model_dump(mode="json")
        for keys, value, text in parsed:
            _apply(data, keys, value, text)
        source = f"{source} with --set {' '.join(overrides)}"
        try:  # an old key given with --set migrates as in a file
            config = ExperimentConfig.model_validate(migrate(data))
        except ValidationError as err:
            raise ConfigError(_format_error(source, err)) from None
        except ValueError as err:
            raise ConfigError(f"{source}: {err}") from None
    return config


def _validated_with_overrides(
    data: dict[str, Any],
    parsed: Sequence[tuple[list[str], Any, str]],
    source: str,
) -> ExperimentConfig | None:
    """The config of a file that is invalid alone, validated with the overrides applied to the
    file as written (``data``, where those of the map keys are already applied); ``None`` when
    there are no other overrides or one does not apply to the file as written
    (``phases.initial...`` on a file without phases: the file's own error is the one to name).

    Raises:
        ConfigError: when the overrides apply but the file with them is still invalid, naming
            the file with its ``--set``s.
    """
    rest = [item for item in parsed if not _replaces_a_map(item[0], item[1])]
    if not rest:
        return None
    data = copy.deepcopy(data)
    try:
        for keys, value, text in rest:
            _apply(data, keys, value, text)
    except (ConfigError, KeyError, TypeError):
        return None
    both = f"{source} with --set {' '.join(text for _, _, text in parsed)}"
    try:
        return ExperimentConfig.model_validate(migrate(data))
    except ValidationError as err:
        raise ConfigError(_format_error(both, err)) from None
    except ValueError as err:
        raise ConfigError(f"{both}: {err}") from None


def _replaces_a_map(keys: Sequence[str], value: Any) -> bool:
    """Whether an override sets (part of) ``env.map`` or ``env.test_maps``, by its key or as a
    key of the ``env`` mapping it gives."""
    if list(keys) == ["env"] and isinstance(value, dict):
        return bool({"map", "test_maps"} & set(value))
    return len(keys) >= 2 and keys[0] == "env" and keys[1] in ("map", "test_maps")


def _apply(data: dict[str, Any], keys: list[str], value: Any, text: str) -> None:
    """:func:`apply_override`, and the hash of a map file an override names anew (or moves away
    from) forgotten: it is the replaced file's, and the new file's is taken when validating."""
    names_map = keys[:2] == ["env", "map"] or (
        keys == ["env"] and isinstance(value, dict) and "map" in value
    )
    env = data.get("env")
    if names_map and isinstance(env, dict):  # first: a hash given beside the map is kept
        env.pop("map_sha256", None)
    apply_override(data, keys, value, text)
    if len(keys) >= 2 and keys[-2:] == ["file", "path"]:
        node: Any = data
        for key in keys[:-1]:
            node = node[_list_index(node, key)] if isinstance(node, list) else node[key]
        node.pop(SHA256, None)
