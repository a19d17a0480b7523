"""The benchmark's physics/CMA-ES overrides (bench/refine.py ``--sim``/``--cma``, bench/speed.py variants)."""

from __future__ import annotations

import argparse
from dataclasses import asdict
from typing import Any

import pytest

from bench.refine import cma_defaults, override_tag, parse_overrides, sim_defaults
from bench.speed import VARIANTS
from worker.refine.losses import DEFAULT_WEIGHTS
from worker.refine.windowed import CmaSettings
from worker.simulation.config import SimConfig


def _parser() -> argparse.ArgumentParser:
    return argparse.ArgumentParser(prog="bench", exit_on_error=False)


def test_overrides_take_the_type_of_the_default() -> None:
    out = parse_overrides(["noslip_iterations=0", "impratio=10", "contact_solimp=0.99,0.995,0.001",
                           "hand_gravcomp=false"], _parser(), "--sim", sim_defaults())
    assert out == {"noslip_iterations": 0, "impratio": 10.0, "contact_solimp": (0.99, 0.995, 0.001),
                   "hand_gravcomp": False}
    assert SimConfig(**out).impratio == 10.0
    assert parse_overrides(["stall_generations=3"], _parser(), "--cma", cma_defaults()) == {"stall_generations": 3}


@pytest.mark.parametrize("pair", ["impratio", "no_such_setting=1", "noslip_iterations=many"])
def test_a_bad_override_is_refused_by_name(pair: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        parse_overrides([pair], _parser(), "--sim", sim_defaults())
    assert "--sim" in capsys.readouterr().err


def test_the_cache_tag_tells_configurations_apart() -> None:
    assert override_tag({}) == ""
    ten, thirty = {"impratio": 10.0, "noslip_iterations": 0}, {"impratio": 30.0, "noslip_iterations": 0}
    assert override_tag(ten) != override_tag(thirty)


def test_every_variant_names_real_settings() -> None:
    sim_fields, cma_fields = SimConfig().to_dict(), asdict(CmaSettings())
    for name, v in VARIANTS.items():
        assert set(v.sim) <= set(sim_fields), name
        assert set(v.cma) <= set(cma_fields), name
        assert set(v.weights) <= set(DEFAULT_WEIGHTS), name
        assert v.what and (v.threads is None or v.threads >= 1), name
        SimConfig(**v.sim)  # constructs


def test_the_restarts_option_reaches_the_cache_key() -> None:
    """``bench/refine.py --restarts N`` keys its cached results apart from the product's default."""
    from bench.refine import parse_args, restarts_tag

    args = parse_args(["--seed", "1000003", "--restarts", "1"])
    assert (args.seed, args.restarts) == (1000003, 1)
    assert restarts_tag(args) == "_r1" and restarts_tag(parse_args([])) == ""


def test_coacd_overrides_reach_the_decomposition_and_its_cache_key(monkeypatch: pytest.MonkeyPatch) -> None:
    """``--coacd threshold=0.04``: typed like the default, applied to the settings ``convex_parts`` reads, and the
    convex cache's key changes with them (parts made with other settings are never read back)."""
    import numpy as np

    from bench.refine import apply_coacd_overrides, parse_args
    from worker.simulation import convex_cache

    monkeypatch.setattr(convex_cache, "COACD_PARAMS", dict(convex_cache.COACD_PARAMS))
    args = parse_args(["--coacd", "threshold=0.04", "--coacd", "max_convex_hull=32"])
    assert args.coacd_overrides == {"threshold": 0.04, "max_convex_hull": 32}
    vertices, faces = np.eye(3), np.array([[0, 1, 2]])
    before = convex_cache.cache_key(vertices, faces)
    apply_coacd_overrides(args.coacd_overrides)
    assert convex_cache.COACD_PARAMS["threshold"] == 0.04 and convex_cache.COACD_PARAMS["max_convex_hull"] == 32
    assert convex_cache.cache_key(vertices, faces) != before
    with pytest.raises(SystemExit):
        parse_args(["--coacd", "no_such=1"])


def test_the_report_names_the_objects_held_until_the_recording_moved_them() -> None:
    from bench.refine import held_until_moved_line

    rows: list[dict[str, Any]] = [{"sequence": "20200709-subject-01__20200709_152240", "object": "037_scissors",
             "object_hold": {"release_frame": 34, "until_recording_moves": True}},
            {"sequence": "s__b", "object": "002_master_chef_can",
             "object_hold": {"release_frame": 20, "until_recording_moves": False}},
            {"sequence": "s__c", "object": "003_cracker_box"}]  # made before the hold was recorded
    line = held_until_moved_line(rows)
    assert "1 of 3: 20200709_152240 (037_scissors)" in line and "cracker" not in line
    assert held_until_moved_line(rows[1:]).endswith("0 of 2")


def test_the_report_counts_the_polish_sweeps_run_and_kept() -> None:
    from bench.refine import parse_args, polish_line

    def attempt(ok: bool, e_t: float, e_r: float, polish: bool = False) -> dict[str, object]:
        a: dict[str, object] = {"success": ok, "E_t": e_t, "E_r": e_r,
                                "paper": {"success": ok, "E_t": e_t, "E_r": e_r}}
        return {**a, "polish": True} if polish else a

    def row(attempts: list[dict[str, object]], kept: dict[str, object]) -> dict[str, object]:
        return {"attempts": attempts, "metrics": {"refined": {"success": kept["success"], "paper": kept["paper"]}}}

    first, better = attempt(False, 4.0, 20.0), attempt(True, 1.0, 3.0, polish=True)
    plain = attempt(True, 0.2, 1.0)
    worse_first, worse = attempt(True, 1.0, 4.0), attempt(True, 1.5, 5.0, polish=True)
    rows = [row([first, better], better), row([plain], plain), row([worse_first, worse], worse_first)]
    line = polish_line(rows)
    assert "run on 2 of 3 sequences, kept on 1" in line
    third = attempt(True, 0.9, 2.5, polish=True)
    assert "run on 2 of 3 sequences, a second on 1, kept on 1" in polish_line(
        [row([first, better, third], third), *rows[1:]])
    assert "E_t 4.00 -> 1.00 cm, E_r 20.00 -> 3.00 deg, 1 failure(s) turned success" in line
    assert polish_line(rows[1:2]) == "* polish sweeps: none run"
    assert parse_args(["--no-polish"]).polish is False and parse_args([]).polish is True
