"""No user-facing text points at the design document or the source (issue #53 item 8): every ``--help`` of every
subcommand, and the whole OpenAPI document (description, summaries, parameter and schema descriptions). The API's
error answers are held to the same in the bad-input corpus test."""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator

import sqlalchemy as sa

from common.cli import build_parser
from common.settings import Settings
from service.app import create_app
from tests.support.user_text import source_references


def _helps(parser: argparse.ArgumentParser, name: str = "hoi-refine") -> Iterator[tuple[str, str]]:
    yield name, parser.format_help()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, child in action.choices.items():
                yield from _helps(child, f"{name} {sub}")


def test_help_texts_name_no_source_and_no_design_document() -> None:
    helps = dict(_helps(build_parser()))
    assert {"hoi-refine refine", "hoi-refine submit", "hoi-refine keys create"} <= set(helps)
    found = {name: refs for name, text in helps.items() if (refs := source_references(text))}
    assert not found, found


def test_the_api_description_names_no_source_and_no_design_document() -> None:
    engine = sa.create_engine("sqlite://")
    try:
        doc = json.dumps(create_app(Settings(database_url="sqlite://"), engine).openapi(), ensure_ascii=False)
    finally:
        engine.dispose()
    assert "Physics-in-the-loop refinement" in doc
    assert not source_references(doc)


def test_the_check_finds_what_it_is_meant_to() -> None:
    assert source_references("see common.job_options.JobOptions")
    assert source_references("as a job queue (DESIGN §2)")
    assert source_references("tolerances (worker/refine/verify_report.py)")
    assert not source_references("`python replay.py` in the folder; results.npz")


def test_every_contact_field_states_its_unit_in_the_schema() -> None:
    engine = sa.create_engine("sqlite://")
    try:
        schema = create_app(Settings(database_url="sqlite://"), engine).openapi()["components"]["schemas"]
    finally:
        engine.dispose()
    fields = schema["ContactPublic"]["properties"]
    units = {"frame": "index", "hand": "side", "body": "hand body", "position_world": ", m", "position_object": ", m",
             "normal": "unit vector", "force": ", N", "torque": "N·m", "depth": ", m",
             "part": "object part"}  # fmt: skip
    assert set(fields) == set(units)
    for name, unit in units.items():
        assert unit in fields[name].get("description", ""), (name, fields[name])
