"""A short real refinement result for the visual tests (issue #18), made once per test session.

The 24-frame built-in grasp-and-lift refined with the default budget and no restarts (about 10 s on 2 loaded
cores): the raw replay drops the box, the refined hand lifts it 20 cm, so a video must show the box rise.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from common.job_options import JobOptions

#: Set to 1 to let tests rewrite the pictures under docs/ (never in CI: it would dirty the tree).
UPDATE_DOCS_ENV = "HOI_REFINE_UPDATE_DOCS"
ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"


def update_docs() -> bool:
    return os.environ.get(UPDATE_DOCS_ENV) == "1"


#: Debian packages of Mesa's EGL and software OpenGL driver (what ``MUJOCO_GL=egl`` needs without a GPU).
GL_PACKAGES = ("libegl1", "libegl-mesa0", "libgl1-mesa-dri")
_PROBE = """
from worker.visual.gl import offscreen_context_class
offscreen_context_class()
import mujoco
model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='.1'/></worldbody></mujoco>")
renderer = mujoco.Renderer(model, 32, 32)
renderer.update_scene(mujoco.MjData(model))
assert renderer.render().shape == (32, 32, 3)
"""


def _gl_works(backend: str | None = None) -> tuple[bool, str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    if backend is not None:
        env.update(MUJOCO_GL=backend, PYOPENGL_PLATFORM=backend)
    run = subprocess.run([sys.executable, "-c", _PROBE], cwd=ROOT, capture_output=True, text=True, timeout=120,
                         env=env)  # fmt: skip
    return run.returncode == 0, run.stderr.strip()[-500:]


def apt_install(*packages: str) -> None:
    """``apt-get install`` (after ``apt-get update`` when the first try fails) when running as root; else nothing."""
    if not (hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("apt-get")):
        return
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    cmd = ["apt-get", "install", "-y", "-q", "--no-install-recommends", *packages]
    if subprocess.run(cmd, env=env, capture_output=True, timeout=900).returncode != 0:
        subprocess.run(["apt-get", "update", "-q"], env=env, capture_output=True, timeout=600)
        subprocess.run(cmd, env=env, capture_output=True, timeout=900)


@pytest.fixture(scope="session")
def offscreen_gl() -> None:
    """Offscreen OpenGL for MuJoCo (EGL, or ``MUJOCO_GL=osmesa``), probed in a subprocess; installs Mesa's EGL with
    apt when it is missing and this runs as root; otherwise the rendering tests skip."""
    ok, why = _gl_works()
    if not ok:
        apt_install(*GL_PACKAGES)
        ok, why = _gl_works()
    if not ok:
        pytest.skip(f"no offscreen OpenGL for MuJoCo here: {why}")


@pytest.fixture(scope="session")
def osmesa_gl() -> None:
    """The OSMesa fallback (Debian's ``libosmesa6``, installed with apt as root when missing), or a skip."""
    ok, why = _gl_works("osmesa")
    if not ok:
        apt_install("libosmesa6")
        ok, why = _gl_works("osmesa")
    if not ok:
        pytest.skip(f"OSMesa is not available here: {why}")


@pytest.fixture(scope="session")
def short_refine_result() -> bytes:
    from worker.example import short_example_sequence
    from worker.refine.run import refine_sequence

    # The product's options, restarts included: the visual tests need the box lifted as the product delivers it,
    # not as one CMA-ES seed happens to (the first attempt usually succeeds, and then no restart runs).
    outcome = refine_sequence(short_example_sequence(), JobOptions())
    return outcome.to_npz_bytes()


@pytest.fixture(scope="session")
def short_hinged_result() -> bytes:
    """A cheap refinement of the 32-frame two-handed hinged box (issue #52): two generations of six per window, no
    restarts or polish (about 10 s); the views need a two-handed articulated result, not a good one."""
    from worker.example.hinged_box import short_hinged_box_sequence
    from worker.refine.run import refine_sequence

    outcome = refine_sequence(short_hinged_box_sequence(), JobOptions(max_generations=2, popsize=6, restarts=0,
                                                                      polish=False))  # fmt: skip
    return outcome.to_npz_bytes()
