"""Several processes, one job, on JAX's own engine (``jax.distributed``).

Commands that make shards or episodes (``generate_data``, ``label_resolution``, ``evaluate``) join a job of K
processes when a launcher started them (SLURM's ``srun``, Open MPI's ``mpirun``: JAX reads their environment) or when
given ``--coordinator HOST:PORT --num-processes K --process-id I`` (``add_args``, ``initialize``). Process I then makes
the shards whose index is I modulo K (``part``), each written atomically into the shared folder, on its own devices;
a rerun resumes as a single process does. Training (``learn.train``, ``learn.regressor``) is data-parallel: each
batch is split over a mesh axis ``"batch"`` spanning every device of every process (``batch_mesh``, ``sharded``) and
the parameters are replicated (``replicated``), so every replica applies the same optax update; process 0 alone
writes checkpoints (``is_writer``).
"""

from __future__ import annotations

import itertools
import os

import jax
import numpy as np
from jax._src import distributed as jax_distributed  # the job's coordination client (barriers without collectives)
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

LAUNCHERS = {"SLURM_NTASKS": "SLURM", "OMPI_COMM_WORLD_SIZE": "Open MPI"}  # size variable -> launcher
BARRIER_TIMEOUT_S = 24 * 3600  # a process may wait this long for the slowest of the job (its last shard)
_barriers = itertools.count()  # every process passes the same barriers in the same order: ids agree


def add_args(parser) -> None:
    """The flags that join a job by hand (a launcher needs none)."""
    group = parser.add_argument_group("several processes (jax.distributed; under srun or mpirun nothing is needed)")
    group.add_argument("--coordinator", metavar="HOST:PORT", default=None,
                       help="address of process 0's coordinator service")
    group.add_argument("--num-processes", type=int, default=None, metavar="K", help="processes in the job")
    group.add_argument("--process-id", type=int, default=None, metavar="I", help="this process, in [0, K)")


def launcher() -> str | None:
    """The launcher that started this process as one of several (its name), or None."""
    for variable, name in LAUNCHERS.items():
        if int(os.environ.get(variable, "1") or 1) > 1:
            return name
    return None


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None) -> tuple[int, int]:
    """Join the job (``jax.distributed.initialize``) when the three are given or a launcher started this process;
    else stay alone. Returns ``part()``. ValueError naming the flag when only some are given or they disagree.
    Call before anything touches a JAX device."""
    given = {"--coordinator": coordinator, "--num-processes": num_processes, "--process-id": process_id}
    if any(v is not None for v in given.values()):
        missing = [k for k, v in given.items() if v is None]
        if missing:
            raise ValueError(f"joining a job by hand needs --coordinator, --num-processes and --process-id; "
                             f"missing {', '.join(missing)}")
        if num_processes < 1 or not 0 <= process_id < num_processes:
            raise ValueError(f"--process-id {process_id} must lie in [0, --num-processes {num_processes})")
        if ":" not in coordinator:
            raise ValueError(f"--coordinator is HOST:PORT, got {coordinator!r}")
    if jax.distributed.is_initialized():
        return part()
    if coordinator is not None or launcher() is not None:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")  # collectives of CPU-only processes
        jax.distributed.initialize(coordinator, num_processes, process_id)
    return part()


def from_args(parser, args) -> tuple[int, int]:
    """``initialize`` from a command's flags (``add_args``); a bad combination is a parser error."""
    try:
        return initialize(args.coordinator, args.num_processes, args.process_id)
    except ValueError as e:
        parser.error(str(e))


def part() -> tuple[int, int]:
    """(I, K): this process and the job's process count; process I makes items I, I + K, I + 2K, ..."""
    return jax.process_index(), jax.process_count()


def is_writer() -> bool:
    """Whether this process writes what the job writes once (checkpoints, summaries): process 0."""
    return jax.process_index() == 0


def barrier(name: str) -> None:
    """Wait until every process of the job reaches the barrier ``name`` (nothing when alone). Through the job's
    coordination service, not a device collective: a process may wait hours for the slowest."""
    if jax.process_count() > 1:
        jax_distributed.global_state.client.wait_at_barrier(f"{name} #{next(_barriers)}", BARRIER_TIMEOUT_S * 1000)


def agree(flag: bool) -> bool:
    """Process 0's ``flag`` on every process (a decision all must take together, e.g. to stop)."""
    if jax.process_count() == 1:
        return flag
    return bool(multihost_utils.broadcast_one_to_all(np.array(flag)))


def batch_mesh(devices=None) -> Mesh:
    """A 1-D mesh named "batch" over ``devices`` (default: every device of every process)."""
    return Mesh(np.array(devices or jax.devices()), ("batch",))


def check_batch(batch: int, mesh: Mesh) -> None:
    """ValueError unless ``batch`` splits evenly over the mesh's devices."""
    if batch % mesh.size:
        raise ValueError(f"batch {batch} must be a multiple of the {mesh.size} devices it is split over; use e.g. "
                         f"{-(-batch // mesh.size) * mesh.size}")


def _place(tree, sharding):
    """Host arrays (the same on every process) -> global arrays; each process fills only its own devices' parts."""
    def one(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])
    return jax.tree.map(one, tree)


def sharded(tree, mesh: Mesh):
    """Every leaf split along its first axis over the mesh's "batch" axis."""
    return _place(tree, NamedSharding(mesh, PartitionSpec("batch")))


def whole(mesh: Mesh) -> NamedSharding:
    """The sharding of an array held whole on every device of the mesh (parameters, optimiser state, metrics)."""
    return NamedSharding(mesh, PartitionSpec())


def replicated(tree, mesh: Mesh):
    """Every leaf whole on every device of the mesh."""
    return _place(jax.device_get(tree), whole(mesh))


def host(tree):
    """A replicated tree as NumPy, read from this process's first copy (works where the tree spans processes)."""
    return jax.tree.map(lambda x: np.asarray(x.addressable_data(0)) if isinstance(x, jax.Array) else x, tree)
