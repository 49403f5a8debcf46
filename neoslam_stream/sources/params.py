"""A source's parameters, checked before a run starts (``neoslam run`` exits 2 with one line, and
leaves no run folder, for a name the source does not take or a value it cannot use).

The parameters a source takes are its factory's: a pydantic model when the class names one
(``params_model``, as the synthetic world's ``SyntheticConfig``), else its signature, whose type
hints carry the constraints (``rate_hz: PositiveFloat``, ``path: ExistingDir``). The check builds a
model from that signature, so a source of your own (``--source package.module:Class``) is checked
by its own annotations too; a signature with ``**kwargs`` accepts any other name.
"""

from __future__ import annotations

import functools
import inspect
import typing
from pathlib import Path
from typing import Annotated, Any

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    PositiveFloat,
    PositiveInt,
    ValidationError,
    ValidationInfo,
    create_model,
)

__all__ = ["ExistingDir", "ExistingPath", "PositiveFloat", "PositiveInt", "SourceParamError", "check_params",
           "params_model"]


class SourceParamError(ValueError):
    """A source parameter the source does not take, or a value it cannot use (one line)."""


def _here(info: ValidationInfo) -> bool:
    """Whether the files are to be found here (not on a host of a split run without the source)."""
    return not info.context or info.context.get("files", True)


def _exists(p: Path, info: ValidationInfo) -> Path:
    if _here(info) and not p.exists():
        raise ValueError(f"{p} does not exist")
    return p


def _is_dir(p: Path, info: ValidationInfo) -> Path:
    if _here(info) and not p.is_dir():
        raise ValueError(f"{p} is no folder" if p.exists() else f"{p} does not exist")
    return p


#: a path that must exist when the run starts (a file or a folder)
ExistingPath = Annotated[Path, AfterValidator(_exists)]
#: a folder that must exist when the run starts
ExistingDir = Annotated[Path, AfterValidator(_is_dir)]


@functools.cache
def params_model(factory: Any) -> type[BaseModel]:
    """The model of ``factory``'s parameters: its ``params_model`` attribute, else one built from
    its signature (unannotated parameters take any value; ``**kwargs``: other names allowed)."""
    own = getattr(factory, "params_model", None)
    if isinstance(own, type) and issubclass(own, BaseModel):
        return own
    init = factory.__init__ if isinstance(factory, type) else factory
    try:
        hints = typing.get_type_hints(init, include_extras=True)
    except Exception:  # a user's annotation that does not resolve here: checked by name only
        hints = {}
    fields: dict[str, Any] = {}
    extra = "forbid"
    for i, (name, p) in enumerate(inspect.signature(init).parameters.items()):
        if i == 0 and isinstance(factory, type):
            continue  # self
        if p.kind is p.VAR_KEYWORD:
            extra = "allow"
        elif p.kind is not p.VAR_POSITIONAL:
            fields[name] = (hints.get(name, Any), ... if p.default is p.empty else p.default)
    config = ConfigDict(extra=extra, arbitrary_types_allowed=True)
    return create_model(f"{getattr(factory, '__name__', 'source')}Params", __config__=config, **fields)


def check_params(factory: Any, params: dict[str, Any], kind: str, files: bool = True) -> None:
    """Raise :class:`SourceParamError` (one line naming each faulty parameter) unless ``params``
    are names ``factory`` takes with values it accepts; ``files`` False: the files they name are
    not looked for (a host of a split run that does not run the source)."""
    model = params_model(factory)
    try:
        model.model_validate(params, context={"files": files})
    except ValidationError as exc:
        raise SourceParamError(f"source {kind}: " + "; ".join(_fault(e, params, model) for e in exc.errors())) from None


def _fault(err: Any, params: dict[str, Any], model: type[BaseModel]) -> str:
    name = ".".join(str(p) for p in err["loc"]) or "parameters"
    top = str(err["loc"][0]) if err["loc"] else ""
    if err["type"] == "extra_forbidden":
        return f"unknown parameter {top!r} (it takes {', '.join(model.model_fields)})"
    if err["type"] == "missing":
        return f"parameter {top!r} is missing"
    msg = err["msg"].removeprefix("Value error, ")
    return f"{name} = {params.get(top)!r}: {msg}" if top in params else f"{name}: {msg}"
