"""Choosing MuJoCo's offscreen OpenGL backend: EGL by default, OSMesa where EGL is missing.

MuJoCo picks its ``GLContext`` from ``MUJOCO_GL`` when ``mujoco`` is first imported and falls back to GLFW,
which needs a display. A worker or a CLI command has usually imported ``mujoco`` long before it renders, so
``offscreen_context_class`` selects the class itself: ``MUJOCO_GL`` when set to ``egl`` or ``osmesa``, else
EGL (Mesa's EGL renders without a GPU or display on these machines). OSMesa needs Debian's ``libosmesa6`` and
``MUJOCO_GL=osmesa`` set before the process starts (PyOpenGL fixes its platform on first use).
"""

from __future__ import annotations

import os
from typing import Any

from common.errors import ConfigurationError

BACKENDS: tuple[str, ...] = ("egl", "osmesa")


def backend_name() -> str:
    """The backend ``offscreen_context_class`` uses: ``MUJOCO_GL`` when it names one of ``BACKENDS``, else egl."""
    chosen = os.environ.get("MUJOCO_GL", "").strip().lower()
    return chosen if chosen in BACKENDS else "egl"


def prefer_offscreen_backend() -> None:
    """Set ``MUJOCO_GL`` / ``PYOPENGL_PLATFORM`` to the offscreen backend when unset: call before the first
    ``import mujoco`` of a process that will render (the CLI's render commands and the preview do)."""
    name = backend_name()
    os.environ.setdefault("MUJOCO_GL", name)
    os.environ.setdefault("PYOPENGL_PLATFORM", name)


def offscreen_context_class() -> Any:
    """The ``GLContext`` class of the chosen backend, installed as the one ``mujoco.Renderer`` creates."""
    from mujoco.rendering.classic import gl_context

    name = backend_name()
    try:
        if name == "osmesa":
            from mujoco.osmesa import GLContext
        else:
            from mujoco.egl import GLContext
    except Exception as exc:  # ImportError, or PyOpenGL already fixed on another platform
        hint = "apt-get install libosmesa6 and set MUJOCO_GL=osmesa" if name == "egl" else "apt-get install libosmesa6"
        raise ConfigurationError(f"offscreen rendering with {name} is unavailable ({exc}); {hint}") from exc
    # mujoco.Renderer reads this module attribute each time it creates a context.
    gl_context.GLContext = GLContext
    return GLContext
