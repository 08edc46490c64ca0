"""Shard files of data and label sets: one ``.npz`` per shard (deflated, fixed member timestamps, so equal arrays
give byte-equal files), written atomically; a set is complete when every shard its config.json promises exists
(``learn.data`` writes data sets, ``commands.label_resolution`` label sets)."""

from __future__ import annotations

import glob
import json
import math
import os
import threading
import zipfile
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from dynres_jax.errors import InputError
from dynres_jax.io.files import atomic_write

SHARD_GLOB = "shard_*.npz"
ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def save_npz(path: str, arrays: dict) -> None:
    """Atomic ``np.savez_compressed`` with fixed member timestamps: equal arrays give byte-equal files."""

    def write(f):
        with zipfile.ZipFile(f, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
            for name, value in arrays.items():
                info = zipfile.ZipInfo(name + ".npy", ZIP_DATE)
                info.compress_type = zipfile.ZIP_DEFLATED
                with z.open(info, "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.asarray(value), allow_pickle=False)

    atomic_write(path, write)


def shard_path(out_dir: str, shard: int) -> str:
    return os.path.join(out_dir, f"shard_{shard:05d}.npz")


def fill(todo: list[int], producers: list[Callable[[int], None]]) -> None:
    """Make every shard of ``todo`` once, in order, each by whichever producer (shard index -> None, e.g. the GPU
    engine and the C workers beside it) is free: each runs on its own thread, taking the next index from one list.
    A producer that raises stops every producer taking more, and its error is raised once the others finish."""
    queue, lock = list(reversed(todo)), threading.Lock()

    def run(produce: Callable[[int], None]) -> None:
        while True:
            with lock:
                if not queue:
                    return
                i = queue.pop()
            try:
                produce(i)
            except BaseException:
                with lock:
                    queue.clear()
                raise

    with ThreadPoolExecutor(len(producers)) as threads:
        for done in [threads.submit(run, p) for p in producers]:
            done.result()


def complete_shards(folder: str, flag: str = "--data", kind: str = "data") -> list[str]:
    """The shard paths of a finished set in ``folder``, every one its config.json promises. kind: "data"
    (generate_data's: ``DataConfig.n_shards``) or "labels" (label_resolution's: ceil(scenes / batch)). InputError
    naming ``flag``, the folder and the first missing shard, or a folder that holds no such set."""
    config_path = os.path.join(folder, "config.json")
    try:
        with open(config_path) as f:
            config = json.load(f)
        found = "data" if "worlds" in config else "labels" if "scenes" in config else "neither"
        if found != kind:
            raise InputError(f"{flag} {folder}: it holds {'no data or label set' if found == 'neither' else found}, "
                             f"not {kind}")
        expected = (math.ceil(config["episodes"] / config["worlds"]) if kind == "data"
                    else math.ceil(config["scenes"] / config["batch"]))
    except InputError:
        raise
    except FileNotFoundError:
        raise InputError(f"{flag} {folder}: no config.json, so no data or label set "
                         "(made by experiments.generate_data or experiments.label_resolution)") from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"{flag} {folder}: its config.json is damaged ({type(e).__name__}: {e})") from None
    paths = [shard_path(folder, s) for s in range(expected)]
    extra = sorted(set(glob.glob(os.path.join(folder, SHARD_GLOB))) - set(paths))
    if extra:
        raise InputError(f"{flag} {folder}: {os.path.basename(extra[0])} lies beyond the {expected} shards its "
                         "config.json promises (a shard of another set?)")
    missing = [p for p in paths if not os.path.exists(p)]
    if missing:
        raise InputError(f"{flag} {folder}: {len(missing)} of its {expected} shards are missing "
                         f"({os.path.basename(missing[0])}{', ...' if len(missing) > 1 else ''}): rerun the command "
                         "that made it with the same --out to finish it")
    return paths


def read_shard(path: str, members=None) -> dict:
    """{name: array} of one shard, reading only ``members`` (default all); InputError naming a damaged file."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in (members or z.files)}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
        raise InputError(f"{path}: damaged shard ({type(e).__name__}: {e})") from None


def iter_shards(data_dir: str, members=None, flag: str = "--data") -> Iterator[tuple[str, dict]]:
    """(path, {name: array}) for every shard of a finished set in ``data_dir`` (``complete_shards``) in shard order,
    reading only ``members`` (default all): an npz member is read when asked for, so counting episodes never reads
    images."""
    for path in complete_shards(data_dir, flag):
        yield path, read_shard(path, members)
