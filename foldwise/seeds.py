"""Derived seeds: every random draw in foldwise comes from a seed derived from its place."""

from __future__ import annotations

import numpy as np


def derive_seed(*parts: int) -> int:
    """A 31-bit seed from integers (an experiment's seed, a purpose, an index...).

    The same parts always give the same seed, and nearby parts give unrelated seeds
    (NumPy's SeedSequence hashing), so a restarted scheduler re-derives exactly what it had.
    """
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1)[0] & 0x7FFFFFFF)
