"""Checkpoints: orbax save / restore of flax NNX modules (and any other pytrees) with a JSON card of the config.

The rest of the code never touches orbax. Layout: ``DIR/<step>/`` holds one item per saved pytree (``module``,
``opt``, ...; a restore reads only those it asks for) and ``meta`` (JSON: the config to rebuild the module, anything
the caller adds). Orbax writes a step to a temporary name and renames it when complete; then
``DIR/<step>/manifest.json`` records every file's SHA-256 (written atomically, last), and a step counts as finished
only with its manifest. Every read checks the step's bytes against it first, so a damaged file (one flipped byte) is
named before orbax touches it. ``latest_step`` is where a training run resumes. Every process of a job reads and
writes on its own (no orbax barriers): a data-parallel run saves host copies from process 0 alone
(``dynres_jax.distributed``) and every process restores.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from collections.abc import Callable
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp
from flax import nnx

from dynres_jax.errors import InputError
from dynres_jax.io import files

MANIFEST = "manifest.json"


class CheckpointError(InputError):
    """A checkpoint that cannot be read into what was asked for (damaged, unfinished, or another model's)."""


class MissingCheckpoint(CheckpointError, FileNotFoundError):
    """No finished checkpoint where one was asked for."""


class _QuietReadOnly(logging.Filter):
    """Drops orbax's warnings that a read-only manager ignores its save options: expected on every restore."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not ("read_only=True" in message or "directory is read only" in message)


logging.getLogger("absl").addFilter(_QuietReadOnly())


def _manager(directory, keep: int | None = 3, read_only: bool = False) -> ocp.CheckpointManager:
    if not read_only:
        os.makedirs(directory, exist_ok=True)  # orbax creates no folder for a manager of one process of several
    alone = ocp.options.MultiprocessingOptions(primary_host=jax.process_index(), active_processes={jax.process_index()})
    options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=False, read_only=read_only,
                                           enable_async_checkpointing=False, multiprocessing_options=alone)
    return ocp.CheckpointManager(os.path.abspath(directory), options=options)


def _hashes(step_dir: str) -> dict[str, str]:
    """SHA-256 of every file under ``step_dir`` but the manifest, by path relative to it."""
    out = {}
    for root, _, names in os.walk(step_dir):
        for name in names:
            path = os.path.join(root, name)
            rel = os.path.relpath(path, step_dir)
            if rel != MANIFEST:
                with open(path, "rb") as f:
                    out[rel] = hashlib.file_digest(f, "sha256").hexdigest()
    return dict(sorted(out.items()))


def _seal_hash(hashes: dict[str, str]) -> str:
    return hashlib.sha256(json.dumps(hashes, sort_keys=True).encode()).hexdigest()


def seal(directory, step: int) -> None:
    """Write ``DIR/<step>/manifest.json``: the SHA-256 of every file of the step, and of that list itself."""
    step_dir = os.path.join(directory, str(step))
    hashes = _hashes(step_dir)
    files.write_json(os.path.join(step_dir, MANIFEST), dict(files=hashes, sha256=_seal_hash(hashes)))


def verify(directory, step: int) -> None:
    """CheckpointError naming the first file of ``DIR/<step>`` whose bytes differ from its manifest (or a file missing,
    added, or a damaged manifest)."""
    step_dir = os.path.join(directory, str(step))
    where = f"checkpoint {str(directory)!r} step {step}"
    try:
        with open(os.path.join(step_dir, MANIFEST)) as f:
            manifest = json.load(f)
        recorded = manifest["files"]
        intact = manifest["sha256"] == _seal_hash(recorded)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CheckpointError(f"{where}: {os.path.join(step_dir, MANIFEST)} is damaged or missing "
                              f"({type(e).__name__}): the folder was damaged, or the save was killed") from e
    if not intact:
        raise CheckpointError(f"{where}: {os.path.join(step_dir, MANIFEST)} is damaged (its own hash differs)")
    found = _hashes(step_dir)
    for rel in sorted(set(recorded) | set(found)):
        if rel not in found:
            raise CheckpointError(f"{where}: {os.path.join(step_dir, rel)} is missing")
        if rel not in recorded:
            raise CheckpointError(f"{where}: {os.path.join(step_dir, rel)} is not in its manifest (added later)")
        if found[rel] != recorded[rel]:
            raise CheckpointError(f"{where}: {os.path.join(step_dir, rel)} is damaged (its SHA-256 differs from the "
                                  "manifest's)")


def _steps(directory) -> list[int]:
    """The steps in ``directory`` whose save finished (orbax renamed the folder and the manifest is written)."""
    if not os.path.isdir(directory):
        return []
    return sorted(int(name) for name in os.listdir(directory)
                  if name.isdigit() and os.path.isfile(os.path.join(directory, name, MANIFEST)))


def latest_step(directory) -> int | None:
    """The newest finished step in ``directory``, or None when there is none (or no directory)."""
    steps = _steps(directory)
    return steps[-1] if steps else None


def save(directory, step: int, state: dict[str, Any], meta: dict, keep: int | None = 3) -> None:
    """Write pytrees ``state`` (e.g. {"model": nnx.State, "opt": ...}) and JSON ``meta`` as ``step``; keeps the
    newest ``keep`` steps. The step's folder is listed whole as a claimed folder's own (``files.record``: orbax writes
    it, not through ``files``), not ``directory``: a file of the user's beside the steps stays on ``--fresh``."""
    unsealed = os.path.join(directory, str(step))
    files.record(unsealed, whole=True)
    if os.path.isdir(unsealed) and step not in _steps(directory):
        shutil.rmtree(unsealed)  # a save killed between orbax's rename and the manifest: unfinished
    with _manager(directory, keep) as mngr:
        items = {name: ocp.args.StandardSave(tree) for name, tree in state.items()}
        mngr.save(step, args=ocp.args.Composite(**items, meta=ocp.args.JsonSave(meta)))
        mngr.wait_until_finished()
    seal(directory, step)


def _step_or_latest(directory, step: int | None) -> int:
    """``step`` (default: the newest), its bytes verified against its manifest."""
    found = latest_step(directory)
    if found is None:
        unsealed = [n for n in os.listdir(directory) if n.isdigit()] if os.path.isdir(directory) else []
        hint = (f"; step {max(unsealed, key=int)} has no {MANIFEST}: its save was killed, or it predates manifests "
                "(if you trust it: dynres_jax.io.ckpt.seal(DIR, STEP))" if unsealed else "")
        if not unsealed and latest_step(os.path.join(directory, "ckpt")) is not None:
            hint = f"; a training run's --out keeps it in ckpt/: give {os.path.join(str(directory), 'ckpt')!r}"
        raise MissingCheckpoint(f"no checkpoint in {str(directory)!r} (missing, empty, or only unfinished saves){hint}")
    step = found if step is None else step
    verify(directory, step)
    return step


def load_meta(directory, step: int | None = None) -> dict:
    """The JSON card of a step (default: the newest)."""
    return _read_meta(directory, _step_or_latest(directory, step))


def _read_meta(directory, step: int) -> dict:
    """``load_meta`` of a step already verified."""
    with _manager(directory, read_only=True) as mngr:
        try:
            return dict(mngr.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"])
        except Exception as e:  # orbax raises many types for unreadable files
            raise CheckpointError(f"checkpoint {str(directory)!r} step {step}: cannot read its card: {e}") from e


def restore(directory, abstract_state: dict[str, Any], step: int | None = None) -> tuple[dict[str, Any], dict]:
    """Read ``state`` into the structure of ``abstract_state`` (shapes and dtypes, e.g. from ``nnx.eval_shape``)
    and the card. ``abstract_state`` may name only some of the saved entries (the model without its optimiser).
    Arrays land on this process's first device, whatever devices wrote them (a GPU checkpoint restores on a CPU).
    Raises FileNotFoundError (nothing there) or CheckpointError (unreadable, or another structure)."""
    return _read(directory, abstract_state, _step_or_latest(directory, step))


def _read(directory, abstract_state: dict[str, Any], step: int) -> tuple[dict[str, Any], dict]:
    """``restore`` of a step already verified."""
    here = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    placed = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=here)
                          if hasattr(x, "shape") else x, abstract_state)
    with _manager(directory, read_only=True) as mngr:
        try:
            items = {name: ocp.args.StandardRestore(tree) for name, tree in placed.items()}
            out = mngr.restore(step, args=ocp.args.Composite(**items, meta=ocp.args.JsonRestore()))
        except Exception as e:
            raise CheckpointError(f"checkpoint {str(directory)!r} step {step} cannot be read as the requested model "
                                  "(its files damaged though its manifest matches them, e.g. resealed after the "
                                  "damage, or another model's shapes): "
                                  f"{type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''}") from e
    return {name: out[name] for name in abstract_state}, dict(out["meta"])


def save_module(directory, step: int, module: nnx.Module, meta: dict, extra: dict[str, Any] | None = None,
                keep: int | None = 3) -> None:
    """Save an NNX module's state (plus ``extra`` pytrees, e.g. the optimiser's) and its card."""
    save(directory, step, {"module": nnx.state(module), **(extra or {})}, meta, keep)


def load_module(directory, build: Callable[[dict], nnx.Module], step: int | None = None,
                extra: dict[str, Any] | None = None) -> tuple[nnx.Module, dict, dict[str, Any]]:
    """Rebuild a module from its card and restore its state: ``build(meta)`` makes a fresh module (it is only traced,
    through ``nnx.eval_shape``, so no parameters are initialised; a ValueError from it, a card of another kind of
    model, becomes a CheckpointError naming the folder). ``extra``: abstract pytrees saved beside it. The step's bytes
    are verified once, before the card is read. Returns (module, meta, restored extra)."""
    step = _step_or_latest(directory, step)
    meta = _read_meta(directory, step)
    try:
        abstract = nnx.eval_shape(lambda: build(meta))
    except (KeyError, TypeError, ValueError) as e:  # the card is another model's: before any restore
        raise CheckpointError(f"checkpoint {str(directory)!r}: {e}") from e
    graphdef, abstract_state = nnx.split(abstract)
    state, meta = _read(directory, {"module": abstract_state, **(extra or {})}, step)
    module_state = state.pop("module")
    shapes = jax.tree.map(lambda x: x.shape, module_state)
    if shapes != jax.tree.map(lambda x: x.shape, abstract_state):
        raise CheckpointError(f"checkpoint {directory!r} holds parameters of other shapes than {type(abstract)}")
    bad = sum(int(np.size(x)) - int(np.isfinite(np.asarray(x)).sum()) for x in jax.tree.leaves(module_state))
    if bad:
        raise CheckpointError(f"checkpoint {directory!r} step {meta.get('step')}: {bad} parameter values are not "
                              "finite (NaN or inf): the files are damaged or the training diverged")
    return nnx.merge(graphdef, module_state), meta, state
