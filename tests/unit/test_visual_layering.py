"""``worker/visual`` is science-side code: importing all of it pulls in no Ray, SQLAlchemy, FastAPI or queue
(DESIGN §4 layering), and ``hoi-refine --help`` does not import MuJoCo through it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MODULES = ["cli", "export", "gl", "playback", "plots", "preview", "render", "rerun_log", "standalone_replay", "video"]
FORBIDDEN = ("ray", "sqlalchemy", "fastapi", "common.queue")


def _loaded_after(code: str) -> set[str]:
    probe = f"import json, sys\n{code}\nprint(json.dumps(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, check=True)
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def test_worker_visual_imports_nothing_of_the_runtime() -> None:
    loaded = _loaded_after("\n".join(f"import worker.visual.{m}" for m in MODULES))
    assert not [m for m in loaded if m in FORBIDDEN or m.startswith(tuple(f"{f}." for f in FORBIDDEN))]


def test_the_cli_registry_does_not_import_mujoco() -> None:
    loaded = _loaded_after("from common.cli import build_parser\nbuild_parser()")
    assert "mujoco" not in loaded and "worker.visual.render" not in loaded
