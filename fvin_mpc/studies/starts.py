"""The episodes' initial conditions, one generator for every study.

Episode 0 starts hanging exactly at rest (the scene's rest orientation, the hard start of a
swing-up); episode ``i ≥ 1`` resets the env with seed ``seed + i`` to a random state whose
``|ω₀|`` is bounded by ``max_omegas[(i − 1) % len(max_omegas)]`` (e.g. calm and spinning starts
in turn). The env draws the state, so the same seed gives the same start in every process.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class EpisodeStart:
    """One episode's initial condition: the env's ``reset_options`` (``None``: at rest) and seed."""

    index: int
    seed: int
    reset_options: dict[str, Any] | None
    max_omega: float


def episode_starts(count: int, seed: int, max_omegas: tuple[float, ...]) -> list[EpisodeStart]:
    """``count`` starts: at rest, then seeded random states cycling through ``max_omegas``."""
    if count < 1 or not max_omegas:
        raise ValueError(f"need count >= 1 and at least one max_omega, got {count} and {max_omegas}")
    starts = [EpisodeStart(0, seed, None, 0.0)]
    for i in range(1, count):
        bound = float(max_omegas[(i - 1) % len(max_omegas)])
        starts.append(EpisodeStart(i, seed + i, {"random": True, "max_omega": bound}, bound))
    return starts
