"""``experiments.evaluate`` with the planner's gradient summed by a plain float scatter-add (``profile_scatter``'s
``float``: fast, does not repeat) instead of the library's exact sum: what determinism costs an evaluation (issue 67;
docs/repeat, "What determinism costs an evaluation"). Timing only; its results are not the project's.

    PYTHONPATH=. python scripts/eval_float.py --task gather --kind almond --episodes 32 ... --out OUT
"""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from profile_scatter import plain_float  # noqa: E402

from dynres_jax.models import propagation  # noqa: E402

propagation.exact_scatter_add = plain_float  # in every process that imports this file (spawned workers too)

if __name__ == "__main__":  # spawned workers import this file as __mp_main__: they must not evaluate
    from dynres_jax.commands import evaluate

    evaluate.main()  # reads sys.argv: runs as the program
