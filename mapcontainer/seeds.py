"""Development and evaluation seeds, kept apart.

Every experiment's reported figures come from seeds at or above :data:`EVAL_SEED0`; development
(tuning, debugging, tests) uses seeds below it. A report made on development seeds says so.
"""

from __future__ import annotations

__all__ = ["EVAL_SEED0", "seed_kind"]

EVAL_SEED0 = 90_000


def seed_kind(first_seed: int) -> str:
    """ "evaluation" for runs from ``first_seed`` >= EVAL_SEED0, else "development"."""
    return "evaluation" if first_seed >= EVAL_SEED0 else "development"
