"""The mapping form of ``env.map``: map sources and weighted mixes, typed from the env's registry.

``env.map`` is a string (``random``, a shipped map's name, a map file) or one of::

    map: {cave: {height: 50, width: 80, rock_share: 0.5}}       # one source, a new map each reset
    map:
      mix:                                                      # one source picked per reset
        - {weight: 2, random: {wall_fraction: [0.15, 0.2]}}
        - {weight: 1, maze: {height: 41, width: 41}}

The kinds and their parameters are not listed here: each kind of
:data:`envs.coverage.generators.GENERATORS` gets a pydantic model made from its constructor's
signature (names, types, defaults), so the registry stays the one owner of the names and a new
generator is configurable as soon as it is registered. Unknown kinds and keys are rejected; a
source's ``height`` and ``width`` default to ``env.height`` and ``env.width``.

A ``file`` source (alone or in a mix) is stored with its absolute path and the SHA-256 of its
content (``{file: {path: /abs/room.txt, sha256: ...}}``, filled in when the config is loaded, as
``env.map_sha256`` is for a map file named by a string): loading the saved config again refuses
a file that changed since. A config saved without the hash gets it then.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import json
import typing
from pathlib import Path
from typing import Any

from pydantic import (
    BaseModel,
    ConfigDict,
    PositiveFloat,
    PositiveInt,
    ValidationError,
    create_model,
    model_validator,
)

from envs.coverage import generators

#: The mix's own key; every other key of a source names a kind of the registry.
MIX = "mix"
#: Size of the placeholder maps a source is built for when checking its parameters alone.
_CHECK_SIZE = 50
#: A ``file`` source's key for its content's hash (not an argument of the generator).
SHA256 = "sha256"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


def _parameters_model(kind: str, cls: type[generators.MapGenerator]) -> type[_Strict]:
    """A pydantic model of a generator's constructor keywords (``height`` and ``width``
    optional: the env's size)."""
    hints = typing.get_type_hints(cls.__init__)
    fields: dict[str, Any] = {}
    for name, param in list(inspect.signature(cls.__init__).parameters.items())[1:]:
        if name in ("height", "width"):
            fields[name] = (PositiveInt | None, None)
        else:
            default = ... if param.default is inspect.Parameter.empty else param.default
            fields[name] = (hints[name], default)
    if issubclass(cls, generators.FileMap):
        fields[SHA256] = (str | None, None)
    return create_model(f"{kind.title()}Source", __base__=_Strict, **fields)


_PARAMETERS: dict[str, type[_Strict]] = {
    kind: _parameters_model(kind, cls) for kind, cls in generators.GENERATORS.items()
}


class _OneKind(_Strict):
    """Exactly one kind of the registry, with its parameters."""

    @model_validator(mode="before")
    @classmethod
    def _known_kinds(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        allowed = set(cls.model_fields)
        known = ", ".join([*_PARAMETERS, *sorted(allowed - set(_PARAMETERS))])
        for key in data:
            if key not in allowed:
                raise ValueError(f"unknown map kind {key!r}; known: {known}")
        given = [k for k in data if k in _PARAMETERS or k == MIX]
        if len(given) != 1:
            kinds = ", ".join([*_PARAMETERS, *([MIX] if MIX in allowed else [])])
            raise ValueError(
                f"give exactly one map kind of {kinds}, got {', '.join(given) or 'none'}"
            )
        # ``{cave: }`` in YAML is ``{cave: None}``: the kind with its defaults.
        return {k: ({} if v is None and k in _PARAMETERS else v) for k, v in data.items()}

    def _kind(self) -> str:
        return next(k for k in [*_PARAMETERS, MIX] if getattr(self, k, None) is not None)

    def build(self, height: int, width: int) -> generators.MapGenerator:
        """The generator; sizes not given are ``height`` x ``width``.

        Raises:
            ValueError: naming the kind, for parameters the generator refuses.
        """
        kind = self._kind()
        params = getattr(self, kind)
        if kind == MIX:
            sources = []
            for i, item in enumerate(params):
                try:
                    sources.append((item.weight, item.build(height, width)))
                except ValueError as exc:
                    raise ValueError(f"{MIX}.{i}.{exc}") from None
            return generators.MixGenerator(sources)
        values = params.model_dump(exclude={SHA256})
        if "height" in values:
            values["height"] = values["height"] or height
            values["width"] = values["width"] or width
        try:
            return generators.GENERATORS[kind](**values)
        except ValueError as exc:
            raise ValueError(f"{kind}: {exc}") from None


_KIND_FIELDS: dict[str, Any] = {kind: (model | None, None) for kind, model in _PARAMETERS.items()}

#: One source of a mix: a weight and one kind.
MixItem = create_model("MixItem", __base__=_OneKind, weight=(PositiveFloat, ...), **_KIND_FIELDS)
#: ``env.map``'s mapping form: one kind, or a mix.
MapSource = create_model(
    "MapSource", __base__=_OneKind, mix=(list[MixItem] | None, None), **_KIND_FIELDS
)


def parse_source(data: dict[str, Any]) -> dict[str, Any]:
    """Check a mapping-form ``env.map`` and return it normalised (every parameter filled in,
    map file paths absolute), as a run's ``config.yaml`` keeps it.

    Raises:
        ValueError: One line naming the key (``mix.1.cave.rocks: ...``).
    """
    try:
        source = MapSource.model_validate(data)
    except ValidationError as err:
        first = err.errors()[0]
        loc = ".".join(str(p) for p in first["loc"])
        msg = first["msg"].removeprefix("Value error, ")
        raise ValueError(f"{loc}: {msg}" if loc else msg) from None
    for i, item in enumerate([source] if source.mix is None else source.mix):
        if item.file is not None:
            _pin_file(item.file, "file" if source.mix is None else f"{MIX}.{i}.file")
    checked = source.model_dump(mode="json", exclude_none=True)
    build_source(checked, _CHECK_SIZE, _CHECK_SIZE)  # the generators' own checks of their values
    return checked


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's content (read in blocks).

    Raises:
        OSError: when it cannot be read.
    """
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _pin_file(params: Any, where: str) -> None:
    """Store a ``file`` source's path absolute with its content's hash; refuse a file whose hash
    differs from the one the config already holds (the map changed since it was saved).

    Raises:
        ValueError: naming ``where`` and the file.
    """
    path = Path(params.path).expanduser().resolve()
    params.path = str(path)
    if not path.is_file():
        return  # the generator names the problem
    try:
        digest = file_sha256(path)
    except OSError as exc:
        raise ValueError(f"{where}: cannot read map file {str(path)!r} ({exc.strerror})") from None
    given = getattr(params, SHA256)
    if given is not None and given != digest:
        raise ValueError(
            f"{where}: map file {str(path)!r} has changed since this config was written "
            f"(sha256 {digest[:12]}..., the config says {str(given)[:12]}...)"
        )
    setattr(params, SHA256, digest)


def build_source(data: dict[str, Any], height: int, width: int) -> generators.MapGenerator:
    """The generator of a (checked) mapping-form ``env.map``; sizes not given are the env's.

    Built once per source and size: the check of an ``env`` section builds it (the generators
    check their own parameters) and the factory's envs reuse that one. A generator keeps no
    state between maps (each draw takes the env's ``rng``; a fixed map is handed out as a copy),
    so envs may share it; a map file's source names its content's hash, so a changed file is
    another source.

    Raises:
        ValueError: naming the kind, for parameters the generator refuses (not kept).
    """
    return _built(json.dumps(data, sort_keys=True), height, width)


@functools.lru_cache(maxsize=64)
def _built(text: str, height: int, width: int) -> generators.MapGenerator:
    """:func:`build_source` of the JSON ``text`` of a source (a key the cache can hash)."""
    return MapSource.model_validate(json.loads(text)).build(height, width)


def describe_map(value: str | dict[str, Any], height: int, width: int) -> str:
    """A short line for a (checked) ``env.map``, for printouts: ``random 50x50``, a shipped map's
    name or a file's path as given, and for the mapping form ``cave 50x100``, ``file room.txt``
    or ``mix by weight: 3 random 50x50, 1 maze 41x41``; sizes not given are ``height`` x
    ``width``."""
    if isinstance(value, str):
        random = generators.RandomMaps.name
        return f"{random} {height}x{width}" if value == random else value
    source = MapSource.model_validate(value)
    if source.mix is None:
        return _describe_kind(source, height, width)
    parts = (f"{item.weight:g} {_describe_kind(item, height, width)}" for item in source.mix)
    return f"{MIX} by weight: {', '.join(parts)}"


def _describe_kind(item: _OneKind, height: int, width: int) -> str:
    kind = item._kind()
    params = getattr(item, kind).model_dump(exclude={SHA256})
    if "height" in params:
        return f"{kind} {params['height'] or height}x{params['width'] or width}"
    if "path" in params:
        return f"{kind} {Path(params['path']).name}"
    return " ".join([kind, *(str(value) for value in params.values())])
