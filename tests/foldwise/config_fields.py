"""Every number a config holds, by dotted key: what the bounds tests sweep."""

from __future__ import annotations

from pydantic import BaseModel


def _numeric_fields(model, prefix=""):
    """(dotted key, field) of every number in the config schema, sections walked."""

    for name, field in model.model_fields.items():
        sections = [t for t in _types(field.annotation) if isinstance(t, type) and issubclass(t, BaseModel)]
        if sections:
            yield from _numeric_fields(sections[0], f"{prefix}{name}.")
        elif _types(field.annotation) & {int, float}:
            yield f"{prefix}{name}", field


def _types(annotation):
    from typing import get_args

    arguments = get_args(annotation)
    return {t for argument in arguments for t in _types(argument)} if arguments else {annotation}


NUMERIC_FIELDS = dict(_numeric_fields(__import__("foldwise.config", fromlist=["ExperimentConfig"]).ExperimentConfig))
