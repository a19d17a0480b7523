"""An integer field of a JSON request validated strictly (no text, no booleans) that still takes ``289.0``.

JSON Schema's ``integer`` is a mathematical integer, so ``289.0`` is one and generated clients may send it; pydantic's
strict mode would refuse it. A float with no fractional part is taken as that integer; ``289.5`` and ``"289"`` are
still refused.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BeforeValidator


def integral_float_as_int(value: Any) -> Any:
    """``value`` as an int when it is a finite float with no fractional part; anything else unchanged."""
    return int(value) if isinstance(value, float) and value.is_integer() else value


JsonInt = Annotated[int, BeforeValidator(integral_float_as_int)]
#: The optional form; the validator wraps the whole union so that a field's bounds stay JSON Schema's
#: minimum/maximum in the document (inside the union pydantic would write them as unknown "ge"/"le" keys).
OptionalJsonInt = Annotated[int | None, BeforeValidator(integral_float_as_int)]
