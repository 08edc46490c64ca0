"""Several processes, one job, on JAX's own engine (``jax.distributed``).

Commands that make shards or episodes (``generate_data``, ``label_resolution``, ``evaluate``) join a job of K
processes when a launcher started them (SLURM's ``srun``, Open MPI's ``mpirun``: JAX reads their environment) or when
given ``--coordinator HOST:PORT --num-processes K --process-id I`` (``add_args``, ``initialize``). Process I then makes
the shards whose index is I modulo K (``part``), each written atomically into the shared folder, on its own devices;
a rerun resumes as a single process does. Joined by hand, the processes first meet on PORT + 1 (``_rendezvous``):
a process that never joins within ``--join-timeout`` is named, and each keeps a connection to process 0 that tells
it at once when a peer dies (kill -9 included), in one line (``errors.JobError``).

Training (``learn.train``, ``learn.regressor``) is data-parallel: each batch is split over a mesh axis ``"batch"``
spanning every device of every process (``batch_mesh``, ``sharded``) and the parameters are replicated
(``replicated``), so every replica applies the same optax update; process 0 alone writes checkpoints
(``is_writer``).
"""

from __future__ import annotations

import atexit
import itertools
import json
import os
import select
import socket
import sys
import threading
import time

import jax
import numpy as np
from jax._src import distributed as jax_distributed  # the job's coordination client (barriers without collectives)
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from dynres_jax.errors import JobError

LAUNCHERS = {"SLURM_NTASKS": "SLURM", "OMPI_COMM_WORLD_SIZE": "Open MPI"}  # size variable -> launcher
JOIN_TIMEOUT_S = 300  # default --join-timeout: how long the processes of a job wait for each other to start
BARRIER_TIMEOUT_S = 24 * 3600  # a process may wait this long for the slowest of the job (its last shard)
_barriers = itertools.count()  # every process passes the same barriers in the same order: ids agree


def add_args(parser) -> None:
    """The flags that join a job by hand (a launcher needs none)."""
    group = parser.add_argument_group("several processes (jax.distributed; under srun or mpirun nothing is needed)")
    group.add_argument("--coordinator", metavar="HOST:PORT", default=None,
                       help="address of process 0's coordinator service")
    group.add_argument("--num-processes", type=int, default=None, metavar="K", help="processes in the job")
    group.add_argument("--process-id", type=int, default=None, metavar="I", help="this process, in [0, K)")
    group.add_argument("--join-timeout", type=float, default=None, metavar="S",
                       help=f"seconds to wait for every process to start (default {JOIN_TIMEOUT_S}); then the missing "
                            "ones are named")


def launcher() -> str | None:
    """The launcher that started this process as one of several (its name), or None."""
    for variable, name in LAUNCHERS.items():
        if int(os.environ.get(variable, "1") or 1) > 1:
            return name
    return None


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None, join_timeout: float = JOIN_TIMEOUT_S) -> tuple[int, int]:
    """Join the job (``jax.distributed.initialize``) when the three are given or a launcher started this process;
    else stay alone. Returns ``part()``. ValueError naming the flag when only some are given or they disagree;
    JobError naming the processes that did not join within ``join_timeout`` seconds (joined by hand).
    Call before anything touches a JAX device."""
    given = {"--coordinator": coordinator, "--num-processes": num_processes, "--process-id": process_id}
    if any(v is not None for v in given.values()):
        missing = [k for k, v in given.items() if v is None]
        if missing:
            raise ValueError(f"joining a job by hand needs --coordinator, --num-processes and --process-id; "
                             f"missing {', '.join(missing)}")
        if num_processes < 1 or not 0 <= process_id < num_processes:
            raise ValueError(f"--process-id {process_id} must lie in [0, --num-processes {num_processes})")
        if ":" not in coordinator or not coordinator.rsplit(":", 1)[1].isdigit():
            raise ValueError(f"--coordinator is HOST:PORT, got {coordinator!r}")
        if not join_timeout > 0:
            raise ValueError(f"--join-timeout must be a positive number of seconds, got {join_timeout}")
    if jax.distributed.is_initialized():
        return part()
    if coordinator is not None or launcher() is not None:
        if coordinator is not None:
            _rendezvous(coordinator, num_processes, process_id, join_timeout)
        jax.config.update("jax_cpu_collectives_implementation", "gloo")  # collectives of CPU-only processes
        jax.distributed.initialize(coordinator, num_processes, process_id,
                                   initialization_timeout=max(1, round(join_timeout)))
        atexit.register(_leave_at_exit)  # registered after JAX's shutdown hook, so it runs before it
    return part()


_peers: dict[int, tuple[socket.socket, int]] = {}  # process id -> (connection, pid): process 0's peers, or process 0
_left: list[socket.socket] = []  # connections of peers that said "bye", or to which this process did: kept open


def _rendezvous(coordinator: str, num_processes: int, process_id: int, timeout: float) -> None:
    """Meet every process of the job on the coordinator's PORT + 1 before JAX does (JAX aborts a process whose peers
    never come, naming none): process 0 waits ``timeout`` s for every other to say its id and pid; a JobError names
    the ones that did not (on every process). Then ``_watch`` keeps the connections."""
    host, port = coordinator.rsplit(":", 1)
    address, deadline = (host, int(port) + 1), time.monotonic() + timeout
    if num_processes == 1:
        return
    if process_id == 0:
        try:
            server = socket.create_server(("", address[1]), reuse_port=False)
        except OSError as e:
            raise JobError(f"process 0 cannot listen on port {address[1]} (--coordinator's port + 1): {e}") from None
        with server:
            while len(_peers) < num_processes - 1 and (left := deadline - time.monotonic()) > 0:
                server.settimeout(left)
                try:
                    conn, _ = server.accept()
                    conn.settimeout(max(left, 1.0))
                    i, pid = map(int, _read_line(conn).split())
                except (OSError, ValueError):
                    continue
                _peers[i] = (conn, pid)
        missing = sorted(set(range(1, num_processes)) - set(_peers))
        for conn, _ in _peers.values():
            conn.sendall((json.dumps(dict(missing=missing, pid=os.getpid())) + "\n").encode())
        if missing:
            joined = ", ".join(f"{i} (pid {pid})" for i, (_, pid) in sorted(_peers.items())) or "none"
            raise JobError(f"process(es) {', '.join(map(str, missing))} of {num_processes} never joined the job at "
                           f"{coordinator} within {timeout:g} s (--join-timeout); joined: 0 (pid {os.getpid()}), "
                           f"{joined}")
    else:
        while True:
            try:
                conn = socket.create_connection(address, timeout=max(deadline - time.monotonic(), 0.1))
                conn.sendall(f"{process_id} {os.getpid()}\n".encode())
                conn.settimeout(max(deadline - time.monotonic(), 0.0) + 5.0)
                answer = json.loads(_read_line(conn))
                break
            except (OSError, ValueError):
                if time.monotonic() > deadline:
                    raise JobError(f"process {process_id}: process 0 (the coordinator at {coordinator}) did not "
                                   f"answer on port {address[1]} within {timeout:g} s (--join-timeout)") from None
                time.sleep(0.2)
        if answer["missing"]:
            raise JobError(f"process(es) {', '.join(map(str, answer['missing']))} of {num_processes} never joined the "
                           f"job at {coordinator} within {timeout:g} s (--join-timeout)")
        _peers[0] = (conn, answer["pid"])
    threading.Thread(target=_watch, daemon=True, name="dynres-peers").start()


def _read_line(conn: socket.socket) -> str:
    data = b""
    while not data.endswith(b"\n"):
        chunk = conn.recv(256)
        if not chunk:
            raise ConnectionError("closed")
        data += chunk
    return data.decode().strip()


def _watch() -> None:
    """Until this process leaves: a peer's connection that closes without its "bye" (``leave``) is a peer lost
    mid-run (killed, crashed, its machine gone). Say which in one line and end this process too (exit status 1),
    rather than wait at the next barrier for JAX's heartbeat to abort it; finished shards and parts are on disk."""
    while _peers:
        sockets = {conn: i for i, (conn, _) in list(_peers.items())}
        try:
            readable, _, _ = select.select(list(sockets), [], [], 1.0)
        except (OSError, ValueError):  # this process closed them: it is leaving
            return
        for conn in readable:
            i = sockets[conn]
            try:
                data = conn.recv(256)
            except OSError:
                data = b""
            if data.startswith(b"bye"):
                _left.append(_peers.pop(i, (conn, 0))[0])
                continue
            if data.startswith(b"lost"):  # process 0 names the peer the job lost
                who, pid = map(int, data.split()[1:3])
            elif not data and i in _peers:
                who, pid = i, _peers[i][1]
            else:
                continue
            for other, (peer, _) in list(_peers.items()):  # process 0 tells the others
                if other != i:
                    try:
                        peer.sendall(f"lost {who} {pid}\n".encode())
                    except OSError:
                        pass
            print(f"dynres: error: process {who} (pid {pid}) of the job was lost mid-run; the work finished so far is "
                  "kept: start every process again with the same command to resume", file=sys.stderr, flush=True)
            os._exit(1)


def _leave_at_exit() -> None:
    """At interpreter exit: ``leave`` after a normal end (SystemExit included); after an uncaught exception (Python
    has set ``sys.last_value``) just close the connections, so the peers stop at once instead of waiting at a barrier
    for JAX's heartbeat."""
    if hasattr(sys, "last_value"):
        for conn, _ in _peers.values():
            conn.close()
        _peers.clear()
    else:
        leave()


def leave() -> None:
    """Tell the job's other processes that this one ends on purpose (not lost); nothing when alone. The connections
    stay open until the process ends (closing one early could reset it before the peer has read "bye")."""
    for conn, _ in list(_peers.values()):
        try:
            conn.sendall(b"bye\n")
        except OSError:
            pass
        _left.append(conn)
    _peers.clear()


def from_args(parser, args) -> tuple[int, int]:
    """``initialize`` from a command's flags (``add_args``); a bad combination is a parser error."""
    if args.join_timeout is not None and args.coordinator is None and launcher() is None:
        parser.error("--join-timeout is read when joining a job (--coordinator, --num-processes, --process-id, or "
                     "a launcher such as srun); this process runs alone")
    try:
        return initialize(args.coordinator, args.num_processes, args.process_id,
                          JOIN_TIMEOUT_S if args.join_timeout is None else args.join_timeout)
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
    return _place(tree, split(mesh))


def split(mesh: Mesh) -> NamedSharding:
    """The sharding of an array split along its first axis over the mesh's "batch" axis (a batch inside jit)."""
    return NamedSharding(mesh, PartitionSpec("batch"))


def whole(mesh: Mesh) -> NamedSharding:
    """The sharding of an array held whole on every device of the mesh (parameters, optimiser state, metrics)."""
    return NamedSharding(mesh, PartitionSpec())


def replicated(tree, mesh: Mesh):
    """Every leaf whole on every device of the mesh."""
    return _place(jax.device_get(tree), whole(mesh))


def host(tree):
    """A replicated tree as NumPy, read from this process's first copy (works where the tree spans processes)."""
    return jax.tree.map(lambda x: np.asarray(x.addressable_data(0)) if isinstance(x, jax.Array) else x, tree)
