"""Where a numeric module's setting comes from: a field of one of its frozen dataclasses
(``GuidedConfig``, ``GuideConfig``, ``BlurConfig``...) made with ``param("section.key")`` is
that user parameter of ``AnonymizeConfig`` (config.py), whose one default and description are
written there; ``derived(fn)`` is a value computed from several of them. ``Cls.of(cfg)``
(``FromParams``) fills every such field from a run's parameters, and the field's default is
the same function applied to the default parameters.

WHY: ``build.py`` used to copy the parameters field by field into these dataclasses, each
with a default of its own (``full_face_threshold`` 0.5 there, 0.4 in the config), and a new
parameter had to be added in two places. Fields that are not user parameters (the modules'
measured constants) stay plain dataclass fields."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import field, fields
from typing import Any, Self, cast

from v2xlake.tasks.anonymize.config import AnonymizeConfig

DEFAULTS = AnonymizeConfig()


def lookup(cfg: AnonymizeConfig, path: str) -> Any:
    """The parameter at ``path`` (``section.key``, or a top-level ``key``)."""
    value: Any = cfg
    for key in path.split("."):
        value = getattr(value, key)
    return value


def derived(of: Callable[[AnonymizeConfig], Any], **metadata: Any) -> Any:
    """A field whose value ``of`` computes from a run's parameters (its default: ``of`` of
    the default parameters). A value without a hash (mutable) becomes a default factory,
    as ``dataclasses`` demands."""
    value = of(DEFAULTS)
    meta = {**metadata, "of": of}
    if type(value).__hash__ is None:
        return field(default_factory=lambda: of(DEFAULTS), metadata=meta)
    return field(default=value, metadata=meta)


def param(path: str, convert: Callable[[Any], Any] | None = None) -> Any:
    """A field that is the user parameter at ``path`` in ``AnonymizeConfig`` (kept in the
    field's metadata as ``param``), passed through ``convert`` when the module takes it in
    another unit (milliseconds -> nanoseconds)."""
    if convert is None:
        return derived(lambda cfg: lookup(cfg, path), param=path)
    return derived(lambda cfg: convert(lookup(cfg, path)), param=path, convert=convert)


class FromParams:
    """Gives a frozen dataclass ``of(cfg)``: every field made with ``param`` or ``derived``
    read from ``cfg``, the others left at their defaults."""

    @classmethod
    def of(cls, cfg: AnonymizeConfig) -> Self:
        """The settings for a run's parameters."""
        values = {f.name: f.metadata["of"](cfg) for f in fields(cast(Any, cls))
                  if "of" in f.metadata}
        return cast(Self, cast(Any, cls)(**values))
