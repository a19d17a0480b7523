"""The built-in examples by name (``hoi-refine demo --example NAME``): no data and no licence needed.

* ``box`` (the default, ``make demo``): a right hand pinches a 0.2 kg box and lifts it 20 cm (``sequences``);
* ``hinged_box``: two hands and an articulated object, the left hand holding a base while the right one opens the
  block hinged on it by about 57 degrees (``hinged_box``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from common.errors import InputError
from common.sequence import Sequence


@dataclass(frozen=True)
class Example:
    name: str
    description: str
    build: Callable[[], Sequence]
    #: A shorter version of the same motion, for quick tests.
    build_short: Callable[[], Sequence]


def _box() -> Example:
    from worker.example.sequences import example_sequence, short_example_sequence

    return Example("box", "the built-in synthetic grasp-and-lift (a right hand pinches a 0.2 kg box and lifts it "
                   "20 cm in 2.4 s; the observed hand has hovering/penetrating fingers and jitter)", example_sequence,
                   short_example_sequence)  # fmt: skip


def _hinged_box() -> Example:
    from worker.example.hinged_box import OPEN_RAD, hinged_box_sequence, short_hinged_box_sequence

    return Example("hinged_box", "the built-in two-handed hinged box (the left hand holds a 0.8 kg base while the "
                   f"right hand opens the 0.15 kg block hinged on it by {OPEN_RAD:g} rad; both observed hands have "
                   "hovering/penetrating fingers and jitter)", hinged_box_sequence, short_hinged_box_sequence)  # fmt: skip


EXAMPLES: dict[str, Callable[[], Example]] = {"box": _box, "hinged_box": _hinged_box}
DEFAULT_EXAMPLE = "box"


def example_named(name: str) -> Example:
    """The example called ``name`` (an ``InputError`` listing the names otherwise)."""
    if name not in EXAMPLES:
        raise InputError(f"no built-in example {name!r}; the examples are {', '.join(EXAMPLES)}")
    return EXAMPLES[name]()
