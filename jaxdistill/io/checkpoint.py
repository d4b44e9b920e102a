"""Checkpoints of the distillation state: save every `ckpt_every` steps and on exit, resume.

A checkpoint is one orbax step directory `<directory>/<step>/` holding two items: "state"
(the state pytree: texels, optimizer state, step, PRNG key) and "config" (the run's flags as
JSON, compared on resume by `compatible` / `check_compatible`).

Completeness: orbax writes a step into `<step>.orbax-checkpoint-tmp`, then finalises it by
stamping `commit_timestamp_nsecs` into `_CHECKPOINT_METADATA`, writing `commit_success.txt`
and renaming the directory to `<step>`. On a local disk orbax itself trusts the rename alone,
so a `<step>` directory left by an interrupted copy would count as a checkpoint; this module
also requires the commit marker inside it (`is_committed`), and never lists, restores or
counts (for `max_to_keep`) a directory without it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import json
import logging
import shutil
import signal
import sys
from pathlib import Path
from typing import Any, Iterable, Iterator

import jax
import numpy as np
import orbax.checkpoint as ocp
from etils import epath
from orbax.checkpoint.path import atomicity_types
from orbax.checkpoint.path import step as step_lib

from jaxdistill.errors import InputError, ProblemList

DEFAULT_IGNORE = ("steps", "resume", "ckpt_every", "out_dir")
_ADVICE = "use the same flags, or a new --out_dir, or drop --resume to start over"
_COMMIT_FILE = atomicity_types.COMMIT_SUCCESS_FILE  # "commit_success.txt"


def is_committed(path) -> bool:
    """Whether the step directory `path` was finalised by orbax (not a partial write)."""
    path = Path(path)
    if atomicity_types.TMP_DIR_SUFFIX in path.name or not path.is_dir():
        return False
    if (path / _COMMIT_FILE).is_file():
        return True
    # Versions that finalised by rename alone still stamped the commit time.
    meta = step_lib.Metadata(step=0, path=epath.Path(path))
    try:
        return meta.commit_timestamp_nsecs is not None
    except (OSError, ValueError, TypeError):
        return False


def _root_cause(err: BaseException) -> str:
    """The first line of the innermost exception (tensorstore's own words, e.g. `OUT_OF_RANGE:
    Error reading "texels/0.0" ...`), without the wrapping spec dumps."""
    while err.__cause__ is not None or (err.__context__ is not None and not err.__suppress_context__):
        err = err.__cause__ or err.__context__
    lines = str(err).strip().splitlines()
    text = lines[0] if lines else type(err).__name__
    return text if len(text) <= 300 else text[:300] + "..."


class _CommittedNameFormat:
    """Orbax's standard `<step>` naming, hiding step directories without the commit marker."""

    def __init__(self):
        self._inner = step_lib.standard_name_format()

    def build_name(self, step: int) -> str:
        return self._inner.build_name(step)

    def find_all(self, base_path) -> Iterator[step_lib.Metadata]:
        return (m for m in self._inner.find_all(base_path) if is_committed(m.path))

    def find_step(self, base_path, step: int) -> step_lib.Metadata:
        meta = self._inner.find_step(base_path, step)
        if not is_committed(meta.path):
            raise ValueError(f"checkpoint {meta.path} is incomplete (no {_COMMIT_FILE})")
        return meta


def is_typed_key(x) -> bool:
    """Whether `x` (an array or a jax.ShapeDtypeStruct) is a typed PRNG key (dtype key<impl>)."""
    return jax.dtypes.issubdtype(getattr(x, "dtype", None), jax.dtypes.prng_key)


def _key_impl(leaf):
    """The PRNG implementation of a typed key array or of its jax.ShapeDtypeStruct."""
    if isinstance(leaf, jax.Array):
        return jax.random.key_impl(leaf)
    found = []
    jax.eval_shape(lambda k: found.append(jax.random.key_impl(k)), leaf)
    return found[0]


def _path_name(path) -> str:
    """`opt_state/0/mu` for a jax key path (dict keys, sequence indices, namedtuple fields)."""
    parts = []
    for k in path:
        for attr in ("key", "idx", "name"):
            if hasattr(k, attr):
                parts.append(str(getattr(k, attr)))
                break
        else:
            parts.append(str(k))
    return "/".join(parts)


def _jsonable(config: dict, what: str) -> dict:
    """`config` after a JSON round trip (tuples become lists); TypeError naming a bad key."""
    if not isinstance(config, dict):
        raise TypeError(f"{what} must be a dict of flag name -> value, got {type(config).__name__}")
    out = {}
    for name, value in config.items():
        try:
            out[str(name)] = json.loads(json.dumps(value))
        except (TypeError, ValueError) as err:
            raise TypeError(f"{what}[{name!r}] = {value!r} is not JSON-able: {err}") from None
    return out


@contextlib.contextmanager
def _quiet_abandoned_reads():
    """While a damaged step is read: the failed read leaves orbax/TensorStore coroutines that
    Python reports as "Exception ignored in: <coroutine ...>" with a traceback when they are
    collected. The damage is reported once, by the caller; these go to the debug log."""
    previous = sys.unraisablehook

    def hook(unraisable):
        logging.getLogger(__name__).debug("ignored while reading a damaged checkpoint: %r", unraisable.exc_value)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        gc.collect()          # collect the abandoned reads now, while the quiet hook is installed
        sys.unraisablehook = previous


class CheckpointStore:
    """Orbax `CheckpointManager` over `directory`, keeping the last `max_to_keep` complete steps.

    The directory is created on the first `save`, so opening a store only to resume from a wrong
    path leaves nothing behind; temp dirs of interrupted saves are deleted at each `save`.
    One writer per directory.
    """

    def __init__(self, directory, max_to_keep: int = 3):
        self.directory = Path(directory).absolute()
        state_handler = ocp.StandardCheckpointHandler()
        json_handler = ocp.JsonCheckpointHandler()
        registry = ocp.handlers.DefaultCheckpointHandlerRegistry()
        registry.add("state", ocp.args.StandardSave, state_handler)
        registry.add("state", ocp.args.StandardRestore, state_handler)
        registry.add("config", ocp.args.JsonSave, json_handler)
        registry.add("config", ocp.args.JsonRestore, json_handler)
        self._name_format = _CommittedNameFormat()
        options = ocp.CheckpointManagerOptions(
            max_to_keep=max_to_keep,
            create=False,
            step_name_format=self._name_format,
        )
        self._mngr = ocp.CheckpointManager(self.directory, options=options, handler_registry=registry)

    # -- saving -------------------------------------------------------------------------------

    def save(self, step: int, state, config: dict, *, wait: bool = True) -> bool:
        """Saves `state` and `config` as step `step`; False (nothing written) if that step is
        already a complete checkpoint. With `wait=False` the write finishes in the background
        (the arrays are copied first, so `state` may change right away); it only counts as a
        checkpoint once finalised."""
        step = int(step)
        config = _jsonable(config, "config")
        self._mngr.wait_until_finished()
        final = self._step_dir(step)
        if is_committed(final):
            return False
        if final.exists():  # left by an interrupted write or copy: never a checkpoint, replace it
            shutil.rmtree(final)
        self._remove_temporary()
        self.directory.mkdir(parents=True, exist_ok=True)
        state = jax.tree.map(lambda x: jax.random.key_data(x) if is_typed_key(x) else x, stored_tree(state))
        saved = self._mngr.save(
            step,
            args=ocp.args.Composite(state=ocp.args.StandardSave(state), config=ocp.args.JsonSave(config)),
            force=True,
        )
        if wait:
            self._mngr.wait_until_finished()
        return bool(saved)

    def _remove_temporary(self) -> None:
        """Deletes orbax temp dirs left by interrupted saves (none of ours is in flight here)."""
        if self.directory.is_dir():
            for path in self.directory.iterdir():
                if step_lib.is_path_temporary(path):
                    shutil.rmtree(path)

    def wait(self) -> None:
        """Blocks until a background save (`wait=False`) is finalised."""
        self._mngr.wait_until_finished()

    # -- querying -----------------------------------------------------------------------------

    def all_steps(self) -> list[int]:
        """The steps of all complete checkpoints, ascending."""
        return sorted(s for s in self._mngr.all_steps() if is_committed(self._step_dir(s)))

    def latest_step(self) -> int | None:
        """The latest complete checkpoint's step, or None."""
        steps = self.all_steps()
        return steps[-1] if steps else None

    # -- restoring ----------------------------------------------------------------------------

    def read_config(self, step: int | None = None) -> dict:
        """The config saved with `step` (default: the latest complete one)."""
        step = self._complete_step(step)
        restored = self._mngr.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))
        return dict(restored.config)

    def restore(self, step: int | None, like) -> tuple[Any, dict]:
        """`(state, config)` of `step` (None: the latest complete one), with the structure,
        shapes and dtypes of `like` (concrete arrays or jax.ShapeDtypeStruct), as arrays on the
        default device; InputError naming each leaf whose shape or dtype differs."""
        step = self._complete_step(step)
        self._check_like(step, like)
        full_like, like = like, stored_tree(like)
        device = jax.local_devices()[0]
        sharding = jax.sharding.SingleDeviceSharding(device)

        def abstract(x):
            if is_typed_key(x):
                x = jax.eval_shape(jax.random.key_data, x)
            return jax.ShapeDtypeStruct(tuple(x.shape), x.dtype, sharding=sharding)

        target = jax.tree.map(abstract, like)
        if isinstance(target, dict):
            # a field stored as None by jaxdistill versions before `stored_tree` (an unused
            # optional part): restored as the None it was, which the current state has too
            saved = self._mngr.metadata(step).item_metadata["state"].tree
            if isinstance(saved, dict):
                target.update({k: None for k, v in saved.items() if v is None and k not in target})
        restored = self._mngr.restore(
            step,
            args=ocp.args.Composite(state=ocp.args.StandardRestore(target), config=ocp.args.JsonRestore()),
        )
        stored = restored.state
        if isinstance(like, dict):
            stored = {k: stored[k] for k in like}
        state = jax.tree.map(
            lambda x, data: jax.random.wrap_key_data(data, impl=_key_impl(x)) if is_typed_key(x) else data,
            like, stored,
        )
        if dataclasses.is_dataclass(full_like):
            state = full_like.replace(**state)
        return state, dict(restored.config)

    def read_texels(self, step: int | None = None) -> np.ndarray:
        """The texels of `step` (None: the latest complete one) as a NumPy array, without knowing
        the state's structure (a viewer following a run), on this machine's first device whatever
        devices or processes wrote it."""
        step = self._complete_step(step)
        sharding = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        tree = self._mngr.metadata(step).item_metadata["state"].tree
        target = jax.tree.map(lambda m: jax.ShapeDtypeStruct(tuple(m.shape), m.dtype, sharding=sharding), tree)
        restored = self._mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(target)))
        return np.asarray(restored.state["texels"])

    def _complete_step(self, step: int | None) -> int:
        self._mngr.wait_until_finished()
        steps = self.all_steps()
        if not steps:
            raise InputError.single(
                self.directory, "--resume",
                f"no complete checkpoint in {self.directory}; --resume needs one "
                "(check --out_dir, or drop --resume to start over)")
        if step is None:
            return steps[-1]
        if int(step) not in steps:
            raise InputError.single(
                self.directory, f"step {int(step)}",
                f"no complete checkpoint for step {int(step)} in {self.directory}; complete steps: {steps}")
        return int(step)

    def damage(self, step: int) -> str | None:
        """Why the complete checkpoint `step` cannot be read back (array or config files damaged
        after the commit: a bad disk, a partial copy), or None when the config and every array
        read. Reads the whole state once, as saved (no target needed)."""
        with _quiet_abandoned_reads():
            return self._damage(int(step))

    def _damage(self, step: int) -> str | None:
        try:
            config = self._mngr.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore())).config
        except Exception as err:  # noqa: BLE001 - any failure to read means the step is unusable; reported
            return f"its saved flags (config/) do not read: {_root_cause(err)}"
        if not isinstance(config, dict):
            return "its saved flags (config/) are not a JSON object"
        sharding = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        try:
            tree = self._mngr.metadata(step).item_metadata["state"].tree
            target = jax.tree.map(lambda m: jax.ShapeDtypeStruct(tuple(m.shape), m.dtype, sharding=sharding), tree)
            restored = self._mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(target)))
            jax.block_until_ready(restored.state)
        except Exception as err:  # noqa: BLE001 - as above
            return _root_cause(err)
        return None

    def set_aside(self, step: int) -> Path:
        """Moves the step's folder out of the store (to `<directory>.damaged/<step>`, kept for
        inspection) so it is never listed again and a new save of that step can be written."""
        source = self._step_dir(step)
        target = self.directory.with_name(self.directory.name + ".damaged") / source.name
        n = 1
        while target.exists():
            target = target.with_name(f"{source.name}.{n}")
            n += 1
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(source), str(target))
        self._mngr.reload()
        return target

    def saved_shapes(self, step: int | None = None) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
        """{leaf path (e.g. "texels", "opt_state/0/mu"): (shape, dtype)} of a complete checkpoint's state."""
        step = self._complete_step(step)
        tree = self._mngr.metadata(step).item_metadata["state"].tree
        return {_path_name(p): (tuple(m.shape), np.dtype(m.dtype))
                for p, m in jax.tree_util.tree_flatten_with_path(tree)[0]}

    def _check_like(self, step: int, like) -> None:
        """InputError for each leaf of `like` missing from, or shaped/typed unlike, the checkpoint."""
        tree = self._mngr.metadata(step).item_metadata["state"].tree
        saved = {_path_name(p): m for p, m in jax.tree_util.tree_flatten_with_path(tree)[0]}
        wanted = {_path_name(p): x for p, x in jax.tree_util.tree_flatten_with_path(stored_tree(like))[0]}
        where = self._step_dir(step)
        problems = ProblemList()
        for name, x in wanted.items():
            if is_typed_key(x):
                x = jax.eval_shape(jax.random.key_data, x)
            meta = saved.get(name)
            if meta is None:
                problems.add(where, name, "missing from the checkpoint (the state layout changed); " + _ADVICE)
                continue
            shape, dtype = tuple(x.shape), np.dtype(x.dtype)
            saved_shape, saved_dtype = tuple(meta.shape), np.dtype(meta.dtype)
            if (shape, dtype) != (saved_shape, saved_dtype):
                problems.add(where, name,
                             f"the checkpoint has shape {saved_shape} {saved_dtype}, the current run "
                             f"expects {shape} {dtype} (did the scene or the texture size change?); "
                             + _ADVICE)
        for name in saved.keys() - wanted.keys():
            problems.add(where, name, "in the checkpoint but not in the current state (the state "
                         "layout changed); " + _ADVICE)
        problems.raise_if_any()

    def _step_dir(self, step: int) -> Path:
        return self.directory / self._name_format.build_name(int(step))

    # -- lifetime -----------------------------------------------------------------------------

    def close(self) -> None:
        """Waits for a background save to finalise and releases orbax's resources."""
        self._mngr.close()

    def __enter__(self) -> "CheckpointStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def stored_tree(state):
    """The pytree a checkpoint stores for `state`: a dataclass state as {field: value} without
    the fields that are None (optional parts such as --reuse_steps' kept x_pred, absent when
    unused), so checkpoints written before such a field existed keep the same layout and read back."""
    if dataclasses.is_dataclass(state) and not isinstance(state, type):
        return {f.name: getattr(state, f.name) for f in dataclasses.fields(state) if getattr(state, f.name) is not None}
    return state


def compatible(saved: dict, current: dict, *, ignore: Iterable[str] = DEFAULT_IGNORE,
               defaults: dict | None = None) -> list[str]:
    """Sorted names of the flags whose values differ between `saved` and `current` (after a JSON
    round trip; a flag present in only one differs), leaving out `ignore`. A flag the checkpoint
    does not record (a newer jaxdistill added it) counts as its value in `defaults`, the value
    that keeps the old behaviour, so an upgrade does not strand a run that uses neither."""
    saved, current = _jsonable(saved, "saved config"), _jsonable(current, "current config")
    if defaults:
        saved = {**{k: v for k, v in _jsonable(defaults, "defaults").items() if k in current}, **saved}
    skip = set(ignore)
    names = (saved.keys() | current.keys()) - skip
    return sorted(n for n in names if n not in saved or n not in current or saved[n] != current[n])


def check_compatible(saved: dict, current: dict, directory, ignore: Iterable[str] = DEFAULT_IGNORE,
                     defaults: dict | None = None) -> None:
    """InputError naming `directory` and each differing flag (saved vs current value); see `compatible`."""
    differ = compatible(saved, current, ignore=ignore, defaults=defaults)
    if not differ:
        return
    saved, current = _jsonable(saved, "saved config"), _jsonable(current, "current config")
    missing = "(not set)"

    def show(cfg, name):
        return json.dumps(cfg[name]) if name in cfg else missing

    problems = [(str(directory), f"--{name}",
                 f"checkpoint has {show(saved, name)}, current run has {show(current, name)}")
                for name in differ]
    problems.append((str(directory), "--resume",
                     f"the checkpoint was written with other flags; {_ADVICE}"))
    raise InputError(problems)


class StopSignals:
    """Context manager turning SIGINT and SIGTERM into a flag (`requested`) that the loop polls
    to save a checkpoint and exit. A second signal goes to the previous handler (a second
    Ctrl-C interrupts at once). Enter it from the main thread; the previous handlers are
    restored on exit."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self._signum: int | None = None
        self._previous: dict[int, Any] = {}

    @property
    def requested(self) -> bool:
        return self._signum is not None

    @property
    def signal_name(self) -> str | None:
        return None if self._signum is None else signal.Signals(self._signum).name

    @property
    def exit_status(self) -> int | None:
        """The shell's status for a process ended by the signal (128 + its number: 130 for SIGINT,
        143 for SIGTERM), so a scheduler can tell a stopped run from a finished one."""
        return None if self._signum is None else 128 + int(self._signum)

    def _handle(self, signum, frame) -> None:
        if self._signum is None:
            self._signum = signum
            return
        previous = self._previous.get(signum)
        if callable(previous):
            previous(signum, frame)
        elif previous == signal.SIG_DFL:
            signal.signal(signum, signal.SIG_DFL)
            signal.raise_signal(signum)

    def __enter__(self) -> "StopSignals":
        self._signum = None
        try:
            for sig in self.SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        except BaseException:
            self._restore()
            raise
        return self

    def _restore(self) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous if previous is not None else signal.SIG_DFL)
        self._previous = {}

    def __exit__(self, *exc) -> None:
        self._restore()
