"""One rule for every algorithm class: its parameters are declared once, in its pydantic model."""

from __future__ import annotations

from typing import Any, TypeVar

from pydantic import BaseModel

C = TypeVar("C", bound=BaseModel)


def make_config(model: type[C], config: C | dict[str, Any] | None, overrides: dict[str, Any]) -> C:
    """The validated config of a component: ``config`` (a model or a dict, default: the model's
    defaults) with keyword ``overrides`` on top, so that ``Cls(config)`` and
    ``Cls(theta_sigma=300)`` both work and both are validated by the same model."""
    if isinstance(config, model) and not overrides:
        return config
    base = config.model_dump() if isinstance(config, BaseModel) else dict(config or {})
    return model(**{**base, **overrides})
