"""The close-up as a stored preview artifact (issue #53 item 7): a job submitted with ``preview_close_up`` gets a
close-up video from the worker's preview beside the default one, its body links it with its media type and the link
serves the video; a job without the option (the default) has no close-up. SQLite (the links of every artifact run on
both backends in test_api_links.py)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from common.job_options import JobOptions
from common.result_format import read_summary
from tests.support.api import json_body
from tests.support.queue_fixtures import ApiHarness
from worker.runtime.jobs import make_artifact_function
from worker.runtime.loop import WorkerLoop


class StoredResult:
    """A worker's job function that returns a refinement result made beforehand (the preview is what is tested)."""

    def __init__(self, blob: bytes) -> None:
        self.blob = blob

    def __call__(self, payload: bytes, options: JobOptions, progress: Any, should_stop: Any) -> tuple[bytes, dict]:
        return self.blob, read_summary(self.blob)


@pytest.mark.usefixtures("offscreen_gl")  # the worker renders the preview
def test_a_job_with_the_option_gets_the_close_up_and_its_link_resolves(
    api: ApiHarness, short_refine_result: bytes, tmp_path: Any
) -> None:
    from worker.visual import read_mp4

    ids: dict[str, str] = {}
    for name, options in (("close", {"preview_close_up": True}), ("default", {})):
        resp = api.client.post("/v1/jobs", json=json_body(len(ids), **options), headers=api.headers)
        assert resp.status_code == 202, resp.text
        ids[name] = resp.json()["id"]
    loop = WorkerLoop(api.queue, StoredResult(short_refine_result), "w", lease_seconds=60, idle_poll_seconds=0.01,
                      artifact_fn=make_artifact_function("refine"))  # fmt: skip
    assert loop.run_once() == "succeeded" and loop.run_once() == "succeeded"

    job = api.client.get(f"/v1/jobs/{ids['close']}", headers=api.headers).json()
    href = f"/v1/jobs/{ids['close']}/close-up"
    assert job["links"]["close_up"] == {"href": href, "type": "video/mp4",
                                        "title": "close-up video: the camera follows the object, the fingers at it"}
    assert href in job["summary"]["preview"]["files"] and f"/v1/jobs/{ids['close']}/video" in job["summary"][
        "preview"]["files"]  # fmt: skip
    entry = next(f for f in job["files"] if f["name"] == "close_up.mp4")
    assert (entry["href"], entry["type"]) == (href, "video/mp4")
    got = api.client.get(href, headers={**api.headers, "Accept": "video/mp4"})
    assert got.status_code == 200 and got.headers["content-type"] == "video/mp4"
    assert len(got.content) == entry["size_bytes"]
    # A video of every frame in the preview's panels, not the default view: the object fills more of it.
    (tmp_path / "close.mp4").write_bytes(got.content)
    (tmp_path / "wide.mp4").write_bytes(api.client.get(job["links"]["video"]["href"], headers=api.headers).content)
    close, _ = read_mp4(tmp_path / "close.mp4")
    wide, _ = read_mp4(tmp_path / "wide.mp4")
    assert close.shape == wide.shape and close.shape[1:] == (480, 1280, 3)
    assert _object_share(close[0]) > 2 * _object_share(wide[0])

    # Off by default: no close-up stored, linked or served.
    default = api.client.get(f"/v1/jobs/{ids['default']}", headers=api.headers).json()
    assert "video" in default["links"] and "close_up" not in default["links"]
    assert all(f["name"] != "close_up.mp4" for f in default["files"])
    missing = api.client.get(f"/v1/jobs/{ids['default']}/close-up", headers=api.headers)
    assert missing.status_code == 404 and "preview" in missing.json()["detail"]


def _object_share(frame: np.ndarray) -> float:
    """The share of the refined (right) panel's pixels showing the solid object."""
    from tests.integration.test_visual import object_pixels

    panel = frame[:, frame.shape[1] // 2:]
    return len(object_pixels(panel)) / (panel.shape[0] * panel.shape[1])


def test_the_option_is_off_by_default_and_on_the_command_line() -> None:
    import argparse

    from common.job_options_cli import add_job_option_arguments, job_options_from_args

    assert JobOptions().preview_close_up is False
    parser = argparse.ArgumentParser()
    add_job_option_arguments(parser, queue=True)
    assert job_options_from_args(parser.parse_args(["--preview-close-up"])).preview_close_up is True
    assert job_options_from_args(parser.parse_args([])).preview_close_up is False
