"""Base of every input schema (presets, friction laws, experiments, campaigns).

:class:`StrictModel` refuses unknown keys and true/false in number fields; ``Pos``, ``NonNeg``,
``Finite`` and ``Fraction`` are the number types with their bounds. Kept apart from
:mod:`stage_sim.config` so that the friction laws (:mod:`stage_sim.friction`), whose schemas
the preset schema is built from, can use them without an import cycle.
"""
from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field

from stage_sim.validation import is_number_type

__all__ = ["Pos", "NonNeg", "Finite", "Fraction", "Number", "StrictModel"]


def _not_bool(value):
    if isinstance(value, bool):
        raise ValueError("expected a number, not true/false")
    return value


Number = BeforeValidator(_not_bool)
"""Refuses true/false where a number is due (pydantic would read them as 1 and 0); every
number field of a :class:`StrictModel` model gets it, these aliases also inside lists."""
Pos = Annotated[float, Number, Field(gt=0, allow_inf_nan=False)]
NonNeg = Annotated[float, Number, Field(ge=0, allow_inf_nan=False)]
Finite = Annotated[float, Number, Field(allow_inf_nan=False)]
Fraction = Annotated[float, Number, Field(ge=0, le=1, allow_inf_nan=False)]


class StrictModel(BaseModel):
    """Base of every input schema (presets, experiments, campaigns): unknown keys are
    refused, and so is true/false in any number field (pydantic alone reads them as 1/0)."""
    model_config = ConfigDict(extra="forbid", frozen=True)

    @classmethod
    def __pydantic_init_subclass__(cls, **kwargs):
        super().__pydantic_init_subclass__(**kwargs)
        numbers = [info for info in cls.model_fields.values()
                   if is_number_type(info.annotation) and Number not in info.metadata]
        for info in numbers:
            info.metadata.append(Number)
        if numbers:
            cls.model_rebuild(force=True)
