"""Flags that each set one config value, declared once with the value's dotted config path.

``ConfigFlags(parser).add("--rate", path="source.rate", help=...)`` adds an option whose type and
choices come from that field of the config model: a ``Literal`` or a ``^(a|b)$`` pattern gives
the choices, a list makes the flag repeatable, a mapping takes a JSON object. ``overrides(args)``
turns the flags given into the nested overrides that ``load_config`` validates, so a bad value
is one ``ConfigError`` line naming the field."""

from __future__ import annotations

import argparse
import json
import re
import types
import typing
from typing import Any

_UNSET = object()


def json_object(text: str) -> dict[str, Any]:
    """argparse type of a mapping-valued flag: a JSON object."""
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise argparse.ArgumentTypeError(f"not JSON ({exc}): {text!r}") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"must be a JSON object such as '{{\"A\": 1}}', got {text!r}")
    return value


def _not_none(tp: Any) -> Any:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0] if len(args) == 1 else tp
    return tp


def option_kwargs(path: str) -> dict[str, Any]:
    """add_argument's type / choices / action for the config field at the dotted ``path`` (a
    mapping's key is a step too: ``bus.capacity.image``)."""
    from ..config import config_model

    tp, info = config_model(), None
    for name in path.split("."):
        if typing.get_origin(tp) is dict:
            tp, info = typing.get_args(tp)[1], None
        else:
            info = tp.model_fields[name]
            tp = _not_none(info.annotation)
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Literal:
        return {"choices": list(args), "type": type(args[0])}
    if origin is list:
        return {"action": "append", "type": args[0]}
    if origin is dict:
        return {"type": json_object}
    for meta in getattr(info, "metadata", ()):
        choices = re.fullmatch(r"\^\(([\w|-]+)\)\$", getattr(meta, "pattern", None) or "")
        if choices:
            return {"choices": choices.group(1).split("|")}
    return {"type": tp} if tp in (int, float) else {}


class ConfigFlags:
    """The flags of one command that set config values (``args.config_flags`` once parsed)."""

    def __init__(self, parser: argparse.ArgumentParser):
        self.parser = parser
        self.flags: list[tuple[str, str, dict[str, Any], Any]] = []  # dest, path, also, convert
        parser.set_defaults(config_flags=self)

    def add(self, *names: str, path: str, help: str, sets: Any = _UNSET, also: dict[str, Any] | None = None,
            convert: Any = None, to: Any = None, **kw: Any) -> None:
        """A flag for the value at ``path``. ``sets``: a switch that sets this value; ``also``: other
        paths it sets too; ``convert``: text -> value (a ValueError is the user's error); ``to``: the
        group to add it to; ``kw``: add_argument's own arguments, over the derived ones."""
        if sets is not _UNSET:
            kw = {"action": "store_const", "const": sets, **kw}
        elif convert is None:
            kw = {**option_kwargs(path), **kw}
        dest = (to or self.parser).add_argument(*names, help=help, **kw).dest
        if all(f[0] != dest for f in self.flags):  # --lossless and --realtime share one
            self.flags.append((dest, path, also or {}, convert))

    def overrides(self, args: argparse.Namespace, fixed: dict[str, Any] | None = None) -> dict[str, Any]:
        """The nested overrides of the flags given (in the order they were added), then ``fixed``
        (dotted paths too); a value that ``convert`` refuses raises ConfigError."""
        from ..config import ConfigError

        values: dict[str, Any] = {}
        for dest, path, also, convert in self.flags:
            if (value := getattr(args, dest, None)) is not None:
                try:
                    values.update({path: convert(value) if convert else value, **also})
                except ValueError as exc:
                    raise ConfigError(str(exc)) from None
        over: dict[str, Any] = {}
        for path, value in {**values, **(fixed or {})}.items():
            *parents, leaf = path.split(".")
            node = over
            for name in parents:
                node = node.setdefault(name, {})
            node[leaf] = value
        return over
