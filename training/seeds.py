"""The evaluation seed, in one place (a module with no imports, so the CLI's parser can read it
without loading the simulator).

Training and selection use other seeds (the profile's collect 0, DAgger 100+k, vision 200+k,
validation 500: ``training.profiles``); everything that reports a landing figure — ``visland
eval``, ``fly``, ``demo``, the suites and the model card — flies episodes of this one.
"""

from __future__ import annotations

__all__ = ["EVAL_SEED"]

EVAL_SEED = 1_000_000
"""Disjoint from every training and selection seed."""
