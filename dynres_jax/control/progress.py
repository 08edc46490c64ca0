"""A closed loop's progress on disk, so an interrupted task command goes on from its last finished step.

``save`` writes a closed loop's ``control.mpc.Progress`` (the records so far, the worlds after the last push, the
planner's warm start) and the GIF frames drawn so far to one ``.npz`` file, atomically, after every step; ``load``
reads it back against a template of the worlds' state (``PileEnv.reset``'s, batched), refusing a file of another
shape. No pickle: the state's leaves are plain arrays, the records JSON.
"""

from __future__ import annotations

import json
import zipfile

import jax
import numpy as np

from dynres_jax.control.mpc import Progress
from dynres_jax.errors import InputError
from dynres_jax.io import files

SCALARS = ("step", "seconds")  # record fields that are one number for the whole batch


def save(path: str, progress: Progress, frames: list[np.ndarray]) -> None:
    """``progress`` and the frames drawn so far (uint8 [H, W, 3] each) to ``path`` (.npz), atomically."""
    records = [{k: v if k in SCALARS else np.asarray(v).tolist() for k, v in r.items()} for r in progress.records]
    leaves = {f"state_{i}": np.asarray(x) for i, x in enumerate(jax.tree.leaves(progress.states))}
    arrays = dict(leaves, init=np.asarray(progress.init), warm=np.asarray(progress.warm),
                  held=np.asarray(progress.held), frames=np.asarray(frames, np.uint8),
                  records=np.asarray(json.dumps(records)))
    files.atomic_write(path, lambda f: np.savez_compressed(f, **arrays))


def load(path: str, template) -> tuple[Progress, list[np.ndarray]]:
    """The ``Progress`` and frames ``save`` wrote to ``path``, its state shaped as ``template``; InputError naming the
    file when it is damaged or holds worlds of another shape (another scene)."""
    treedef, shapes = jax.tree.structure(template), [np.shape(x) for x in jax.tree.leaves(template)]
    try:
        with np.load(path, allow_pickle=False) as data:
            leaves = [data[f"state_{i}"] for i in range(len(shapes))]
            if [x.shape for x in leaves] != shapes:
                raise ValueError("its worlds have other shapes")
            records = [{k: v if k in SCALARS else np.asarray(v) for k, v in r.items()}
                       for r in json.loads(str(data["records"]))]
            warm = bool(data["warm"]) if data["warm"].ndim == 0 else data["warm"].copy()  # one for all, or [B]
            progress = Progress(records, jax.tree.unflatten(treedef, leaves), data["init"], warm, data["held"].copy())
            return progress, list(data["frames"])
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as e:
        raise InputError(f"{path!r}: an interrupted episode's progress that cannot be read ({e}); delete it or run "
                         "with --fresh") from None
