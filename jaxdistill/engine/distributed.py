"""More than one process: `jax.distributed` behind three flags, and batches each process fills
with its own views.

One process per host (or per GPU) runs the same command with `--coordinator_address=HOST:PORT
--num_processes=N --process_id=I` (or `--coordinator_address=auto`, which lets JAX read them from
SLURM, Open MPI or Kubernetes). `initialize` joins them before JAX touches a device; then
`jax.devices()` is every process's devices and the loop's 1-D "data" mesh spans them all. The
step is unchanged: texels and optimizer state replicated, each step's views split over the
devices by view, XLA all-reducing the gradients (gloo on CPU, NCCL on GPU).

Each process holds one share of the views (`view_share`: view i in share i mod N) and a step
draws its views evenly from the shares, process q's rows from share q (`engine/problem.py`
`Problem.view_ids`), so each process assembles only its own rows of a step's batch
(`place_batch`) from views it holds. The set-up follows: a process other than the primary ray
casts, plans and reads the photos, targets and photo latents of its share alone (`held_views`),
and takes what depends on every view (the texture layout and texel space, then the view counts)
from the primary (`from_primary`, which carries the primary's refusals too). The primary still
holds every view: its evaluation during the loop and the outputs after it (scores, renders,
evidence, pages, glTF) read them all. Where the processes arrive minutes apart (the hand-over,
the loop's start, the end of the outputs) they meet at a `barrier` first; a process that stops
on an error says so there (`announce_failure`), and the others stop with it, naming the file and
field where it was bad input. Checkpoints are
written by orbax's multi-process protocol (every process calls save; the primary writes the
replicated arrays), and the outputs by the primary alone (`is_primary`).
"""

from __future__ import annotations

import io
import json
import re
import time
from collections.abc import Callable

import jax
import numpy as np
from absl import logging

from jaxdistill.errors import InputError

AUTO = "auto"
_ADDRESS = re.compile(r"^\[?[A-Za-z0-9_.:-]+\]?:(\d{1,5})$")


def address_problem(address: str, num_processes: int, process_id: int) -> list[tuple[str, str]]:
    """[(flag, what is wrong)] of the multi-process flags; empty when they are usable (no address:
    one process, the others must stay at their defaults)."""
    problems = []
    if not address:
        if num_processes != 1:
            problems.append(("num_processes", f"is {num_processes}, but --coordinator_address is empty; give "
                             "--coordinator_address=HOST:PORT of process 0 (or auto under SLURM/Open MPI/Kubernetes)"))
        if process_id not in (-1, 0):
            problems.append(("process_id", f"is {process_id} without --coordinator_address"))
        return problems
    if address == AUTO:
        return problems
    match = _ADDRESS.match(address)
    if not match or not 0 < int(match.group(1)) < 65536:
        problems.append(("coordinator_address", f"{address!r} is not HOST:PORT (e.g. 10.0.0.1:1234 or "
                         "node001:1234), or auto"))
    if num_processes < 2:
        problems.append(("num_processes", f"must be >= 2 with --coordinator_address={address}, got {num_processes}"))
    elif not 0 <= process_id < num_processes:
        problems.append(("process_id", f"must be in [0, {num_processes}) with --num_processes={num_processes}, got "
                         f"{process_id}"))
    return problems


def initialize(address: str, num_processes: int, process_id: int) -> None:
    """Joins the run's processes (nothing for one process). Call before any JAX computation; on CPU
    the collectives go through gloo."""
    if not address:
        return
    try:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    except (AttributeError, KeyError, ValueError):      # a JAX whose CPU collectives are gloo without the option
        logging.info("jax_cpu_collectives_implementation is not an option of this JAX; its CPU default is used")
    if address == AUTO:
        try:
            jax.distributed.initialize()
        except (ValueError, RuntimeError) as err:
            raise InputError.single("flags", "--coordinator_address", (
                f"auto found no cluster to join ({err}); under SLURM, Open MPI or Kubernetes start one process per "
                "host with srun/mpirun, or give HOST:PORT of process 0 with --num_processes and --process_id")) from None
    else:
        jax.distributed.initialize(coordinator_address=address, num_processes=num_processes, process_id=process_id)
    logging.info("process %d of %d: %d local of %d devices", jax.process_index(), jax.process_count(),
                 jax.local_device_count(), jax.device_count())


def is_primary() -> bool:
    """Whether this process writes the run's outputs (process 0; the only one without --coordinator_address)."""
    return jax.process_index() == 0


def local_rows(sharding: jax.sharding.Sharding, rows: int) -> tuple[int, int]:
    """(start, stop) of the leading-axis rows of a (rows, ...) array that `sharding` puts on this
    process's devices (contiguous: the mesh orders devices by process)."""
    spans = [(idx[0].start or 0, rows if idx[0].stop is None else idx[0].stop)
             for idx in sharding.addressable_devices_indices_map((rows,)).values()]
    return min(s for s, _ in spans), max(e for _, e in spans)


def place_batch(make_batch, view_ids: np.ndarray, sharding: jax.sharding.Sharding) -> dict:
    """`make_batch(view_ids)` ({name: (B, ...)} host arrays) on the devices, split by view over
    `sharding`'s mesh. With several processes each assembles and sends only the rows of the views
    its own devices hold."""
    view_ids = np.asarray(view_ids)
    if jax.process_count() == 1:
        return jax.device_put(make_batch(view_ids), sharding)
    start, stop = local_rows(sharding, len(view_ids))
    local = make_batch(view_ids[start:stop])
    return jax.tree.map(lambda x: jax.make_array_from_process_local_data(
        sharding, np.asarray(x), (len(view_ids),) + np.shape(x)[1:]), local)


def view_share(num_views: int, share: int, shares: int) -> np.ndarray:
    """The views (ascending ids) of share `share` of `shares`: view i is in share i mod `shares`,
    so the shares' sizes differ by one at most and each spans the whole capture."""
    return np.arange(share, num_views, shares)


def shares_of_run(view_shares: int) -> int:
    """The shares a run draws its views from: --view_shares, or one per process when it is 0."""
    return view_shares or jax.process_count()


def held_views(num_views: int) -> np.ndarray | None:
    """The views whose per-view arrays this process builds: None (every view) for the primary and a
    one-process run, else the process's share."""
    if jax.process_count() == 1 or is_primary():
        return None
    return view_share(num_views, jax.process_index(), jax.process_count())


_CHUNK = 1 << 30        # bytes a collective carries at most
BARRIER_TIMEOUT_S = 24 * 3600     # how long a process waits for the others at a `barrier`
POLL_S = 0.2            # how often a process at a `barrier` asks who has arrived and who has failed
_KEYS = "jaxdistill/"   # this run's keys in the coordination service's key-value store


class PeerFailed(RuntimeError):
    """Another process of the run stopped with an error other than bad input (its log has the rest)."""


class PeerInputError(InputError):
    """Bad input another process of the run found (each problem says which process)."""


def barrier(name: str) -> None:
    """Waits until every process reaches the barrier `name` (nothing for one process), or stops
    with the error of a process that failed (`announce_failure`): an `InputError` naming the file
    and field that process found wrong, else `PeerFailed`. The processes reach some points minutes
    apart (process 0 sets up every view and writes the outputs), while XLA's CPU collectives give
    up after 30 s when a peer is late to its first one and `jax.distributed` after 300 s of a
    peer's shutdown: so the run meets here, through the coordination service's key-value store
    (each process sets its key, then polls every `POLL_S`), with a day's timeout, before it works
    together. A process that dies without a word (killed) fails the others through the service's
    heartbeats (100 s)."""
    if jax.process_count() == 1:
        return
    client = _state().client
    _barriers[name] = _barriers.get(name, 0) + 1               # every process passes them in the same order
    folder = f"{_KEYS}barrier/{name}_{_barriers[name]}/"
    client.key_value_set(f"{folder}{jax.process_index()}", "")
    deadline = time.monotonic() + BARRIER_TIMEOUT_S
    while True:
        _raise_failures(client, client.key_value_dir_get(f"{_KEYS}failed/"))
        if len(client.key_value_dir_get(folder)) == jax.process_count():
            return
        if time.monotonic() > deadline:
            raise PeerFailed(f"the processes did not all reach '{name}' within {BARRIER_TIMEOUT_S} s")
        time.sleep(POLL_S)


_barriers: dict[str, int] = {}      # how often this process reached each barrier (their ids must not repeat)


def announce_failure(err: BaseException) -> None:
    """Tells the run's other processes that this one stops with `err`: each stops with it at its
    next `barrier` instead of waiting there for this one (nothing for one process, or before the
    processes joined; nothing for what it learnt from another process). Before the loop, it then
    waits (up to `BARRIER_TIMEOUT_S`) until every other process has read it: JAX's shutdown at exit
    waits only 300 s for them, and a set-up can take longer to reach its next barrier. Once the
    loop has begun the others may be inside a step's collectives, which never read it: no wait."""
    state = _state()
    client, count, me = state.client, state.num_processes or 1, state.process_id or 0
    if client is None or count == 1 or isinstance(err, (PeerFailed, PeerInputError)):
        return
    record = {"problems": err.problems} if isinstance(err, InputError) else {"error": f"{type(err).__name__}: {err}"}
    text = json.dumps(record, default=str)
    try:
        client.key_value_set(f"{_KEYS}failed/{me}", text)
        if "loop" in _barriers:
            return
        logging.warning("waiting until the other processes (%d) have read that this one stops", count - 1)
        others, deadline = set(range(count)) - {me}, time.monotonic() + BARRIER_TIMEOUT_S
        # done when each has read it, or failed itself (it reaches no barrier, where it would read it)
        while not others <= _processes(client, f"{_KEYS}seen/{me}/") | _processes(client, f"{_KEYS}failed/"):
            if time.monotonic() > deadline:
                break
            time.sleep(POLL_S)
    except Exception as why:        # noqa: BLE001 -- the service may be gone (process 0 ended); nothing else to do
        logging.warning("could not tell the other processes that this one failed: %s", why)


def _processes(client, folder: str) -> set[int]:
    """The processes with a key in `folder` of the key-value store (keys end in a process id)."""
    return {_process_of(key) for key, _ in client.key_value_dir_get(folder)}


def _process_of(key: str) -> int:
    """The process id a key-value store key ends in."""
    return int(key.rsplit("/", 1)[1])


def _raise_failures(client, entries: list[tuple[str, str]]) -> None:
    """The failures other processes announced (key-value entries `failed/<process>`), raised
    after telling `client` they were read (`seen/<process>/<this process>`): an InputError of
    their problems, each marked with the process that found it, if any was bad input, else
    PeerFailed."""
    problems, errors = [], []
    for key, value in sorted(entries, key=lambda kv: _process_of(kv[0])):
        process, record = _process_of(key), json.loads(value)
        client.key_value_set(f"{_KEYS}seen/{process}/{jax.process_index()}", "")
        where = f"found by process {process} of {jax.process_count()}"
        if "problems" in record:
            problems += [(file, field, f"{message} ({where})") for file, field, message in record["problems"]]
        else:
            errors.append(f"process {process} of {jax.process_count()} stopped: {record['error']}")
    if problems:
        raise PeerInputError(problems)
    if errors:
        raise PeerFailed("; ".join(errors) + " (its log has the traceback); this process stops too")


def _state():
    """`jax.distributed`'s state: the coordination service's client (None before the processes
    joined, which JAX's own multi-process tests use too), the process count and id."""
    from jax._src import distributed as jax_distributed

    return jax_distributed.global_state


def from_primary(make: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """`make()`'s arrays, computed by the primary process alone and received by every other (one
    process: `make()`). Every process must call it at the same point of the set-up. The arrays go
    as one `np.savez` buffer, its length first, in collectives of at most 1 GiB; an `InputError`
    that `make()` raises goes instead, and every process raises it (none is left waiting)."""
    if jax.process_count() == 1:
        return make()
    from jax.experimental import multihost_utils

    barrier("from_primary")             # the primary may take minutes longer: meet before the collectives
    data, made, refused = np.zeros(0, np.uint8), None, None
    if is_primary():
        try:
            made = make()
            payload = made
        except InputError as err:
            refused = err
            payload = {"input_error": np.frombuffer(json.dumps(err.problems).encode(), np.uint8)}
        buffer = io.BytesIO()
        np.savez(buffer, **payload)
        data = np.frombuffer(buffer.getbuffer(), np.uint8)
    size = multihost_utils.broadcast_one_to_all(np.array([len(data) >> 31, len(data) & (2 ** 31 - 1)], np.int32))
    size = (int(size[0]) << 31) | int(size[1])
    received = data if is_primary() else np.empty(size, np.uint8)
    for start in range(0, size, _CHUNK):
        part = data[start:start + _CHUNK] if is_primary() else np.zeros(min(_CHUNK, size - start), np.uint8)
        part = multihost_utils.broadcast_one_to_all(part)
        if not is_primary():
            received[start:start + len(part)] = np.asarray(part, np.uint8)
    if refused is not None:
        raise refused
    if made is not None:
        return made
    with np.load(io.BytesIO(received.tobytes())) as arrays:
        if "input_error" in arrays.files:
            raise InputError([tuple(p) for p in json.loads(arrays["input_error"].tobytes().decode())])
        return {name: arrays[name] for name in arrays.files}
