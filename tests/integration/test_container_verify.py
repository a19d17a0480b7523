"""``hoi-refine verify`` inside the project's container image (issue #54 item 2), run as README documents it
(``docker run ... -v DIR:/data:ro IMAGE hoi-refine verify /data``): an honest result passes there, also stepwise with
other NumPy / OpenBLAS kernels forced, and a forged one fails naming its field and frame.

Skips in well under a second without the docker CLI, a Docker engine that answers, or the image (``make image``
builds it: minutes, so no test does). ``HOI_REFINE_TEST_IMAGE`` names another image (default hoi-refine:latest).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.support.results import cheap_result, forged

pytestmark = pytest.mark.slow

IMAGE = os.environ.get("HOI_REFINE_TEST_IMAGE", "hoi-refine:latest")
#: NumPy's AVX-512 kernels off and OpenBLAS's Haswell kernels: what an AVX2 host runs (as test_verify_stepwise).
OTHER_KERNELS = {"NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR AVX512_SKX", "OPENBLAS_CORETYPE": "Haswell"}


@pytest.fixture(scope="module")
def docker_image() -> list[str]:
    """``docker run`` as the tests use it (no network: verify needs none); skips where it cannot run."""
    docker = shutil.which("docker")
    if docker is None:
        pytest.skip("no docker CLI")
    try:
        probe = subprocess.run([docker, "image", "inspect", "--format", "{{.Id}}", IMAGE], capture_output=True,
                               text=True, timeout=10)  # fmt: skip
    except subprocess.TimeoutExpired:
        pytest.skip("the Docker engine does not answer within 10 s")
    if probe.returncode != 0:
        last = (probe.stderr.strip().splitlines() or ["?"])[-1]
        pytest.skip(f"no Docker engine or no image {IMAGE} (make image): {last}")
    return [docker, "run", "--rm", "--network", "none", "-e", "COLUMNS=200"]


def _folder(path: Path, files: dict[str, bytes]) -> Path:
    path.mkdir(mode=0o755)
    path.chmod(0o755)  # whatever the umask: the image's user reads it through the read-only mount
    for name, blob in files.items():
        (path / name).write_bytes(blob)
        (path / name).chmod(0o644)
    return path


def test_verify_in_the_image_passes_the_honest_and_fails_the_forged(docker_image: list[str], tmp_path: Path) -> None:
    honest = cheap_result(seed=0)
    data = _folder(
        tmp_path / "data",
        {"honest.result.npz": honest, "wrist.result.npz": forged(honest, "right_wrist_pos", 0.05, from_frame=6)},
    )
    report_dir = tmp_path / "report"
    report_dir.mkdir()
    report_dir.chmod(0o777)  # the image's user (uid 10001) writes the report

    run = subprocess.run([*docker_image, "-v", f"{data}:/data:ro", "-v", f"{report_dir}:/report", IMAGE,
                          "hoi-refine", "verify", "/data", "--jobs", "1", "--report", "/report/verify.json"],
                         capture_output=True, text=True, timeout=600)  # fmt: skip

    assert run.returncode == 1, run.stdout + run.stderr
    report = json.loads((report_dir / "verify.json").read_text())
    files = {f["path"]: f for f in report["files"]}
    assert files["honest.result.npz"]["status"] == "passed", files["honest.result.npz"]
    wrist = [f for f in files["wrist.result.npz"]["failures"] if f["field"] == "right_wrist_pos"]
    assert wrist and wrist[0]["frame"] == 6, files["wrist.result.npz"]["failures"]


def test_verify_in_the_image_with_other_kernels_passes_stepwise(docker_image: list[str], tmp_path: Path) -> None:
    data = _folder(tmp_path / "data", {"honest.result.npz": cheap_result(seed=0)})
    env = [a for k, v in OTHER_KERNELS.items() for a in ("-e", f"{k}={v}")]

    run = subprocess.run([*docker_image, *env, "-v", f"{data}:/data:ro", IMAGE,
                          "hoi-refine", "verify", "/data/honest.result.npz"],
                         capture_output=True, text=True, timeout=600)  # fmt: skip

    assert run.returncode == 0, run.stdout + run.stderr
    assert "stepwise state_sim: " in run.stdout and "stepwise raw_state_sim: " in run.stdout, run.stdout
    assert "verify: OK" in run.stdout, run.stdout
