"""What a refinement result records of the environment that made it (``summary.versions``): the raw replay's
packages and CPU kind (``worker.simulation.replay.versions``) plus the optimiser's version. Its own module so that
both ``result`` (which writes it) and ``verify`` (which compares it with its own) can import it."""

from __future__ import annotations

import cma

from worker.simulation.replay import versions as replay_versions


def versions() -> dict[str, str]:
    """The raw replay's package versions and CPU kind plus the optimiser's."""
    return {**replay_versions(), "cma": str(cma.__version__).split()[0]}
