"""More than one process (`engine/distributed.py`): two CPU processes on localhost, joined by
`jax.distributed` (gloo collectives), each holding its share of the views and sending its half of
every step's views, give the texels of one process running the same batches (--view_shares=2);
the checkpoint they write once resumes in one process; bad multi-process flags are named before
any compute; bad input one process alone finds stops every process, naming it."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import jax
import jax.tree as jax_tree
import numpy as np
import pytest

from jaxdistill import pipeline
from jaxdistill.engine import config as config_lib, distributed
from jaxdistill.engine.problem import Problem
from jaxdistill.engine.config import DistillConfig
from jaxdistill.errors import InputError
from jaxdistill.io.checkpoint import CheckpointStore
from tiny_scene import write_tiny_scene
from tolerance import assert_close

REPO = Path(__file__).resolve().parents[1]
STEPS = 4
FLAGS = dict(prior="views", steps=STEPS, views_per_step=2, log_every=2, renders=False, contact_views=0, seed=3)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def texels(out: Path) -> np.ndarray:
    with CheckpointStore(out / "checkpoints") as store:
        return store.read_texels()


def run_two(scene: Path | list[Path], out: Path, cache: Path, flags: dict, timeout: int = 300) -> list[tuple[int, str]]:
    """(return code, log) of two processes of the main job on localhost, joined by jax.distributed;
    `scene` a list: each process's own copy (as on hosts without a shared file system)."""
    scenes = scene if isinstance(scene, list) else [scene, scene]
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXDISTILL_CACHE": str(cache)}
    env["XLA_FLAGS"] = " ".join(f for f in env.get("XLA_FLAGS", "").split()     # one CPU device per process
                                if not f.startswith("--xla_force_host_platform_device_count"))
    env.pop("JAXDISTILL_RGBX_DIR", None)
    address = f"localhost:{free_port()}"
    args = [f"--{k}={str(v).lower() if isinstance(v, bool) else v}" for k, v in flags.items()]
    procs = [subprocess.Popen([sys.executable, "-m", "jaxdistill.main", f"--scene={scenes[i]}", f"--out_dir={out}", *args,
                               f"--coordinator_address={address}", "--num_processes=2", f"--process_id={i}"],
                              cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for i in range(2)]
    logs = []
    for proc in procs:
        try:
            logs.append(proc.communicate(timeout=timeout)[0])
        except subprocess.TimeoutExpired:
            for p in procs:
                p.kill()
            pytest.fail(f"the two processes did not finish in {timeout} s")
    return [(proc.returncode, log) for proc, log in zip(procs, logs)]


@pytest.fixture(scope="module")
def two_process_run(tmp_path_factory):
    work = tmp_path_factory.mktemp("distributed")
    scene = write_tiny_scene(work / "scene")
    out = work / "two"
    results = run_two(scene, out, work / "cache", FLAGS)
    for i, (code, log) in enumerate(results):
        assert code == 0, f"process {i} failed:\n{log[-4000:]}"
    return scene, out, [log for _, log in results]


def test_process_0s_refusal_stops_every_process_with_its_message(tmp_path):
    """Process 0 checks what depends on every view (here: no view sees the mesh) and the others
    wait for its layout: its InputError reaches them, and both stop with it, none left waiting."""
    scene = write_tiny_scene(tmp_path / "scene")
    doc = json.loads(scene.read_text())
    for view in doc["views"]:
        view["c2w"] = [[1, 0, 0, 50], [0, 1, 0, 50], [0, 0, 1, 50], [0, 0, 0, 1]]     # far outside, facing away
    scene.write_text(json.dumps(doc))
    results = run_two(scene, tmp_path / "o", tmp_path / "cache", FLAGS, timeout=120)
    for code, log in results:
        assert code != 0 and "views: no view sees the mesh" in log, log[-3000:]


def test_bad_input_one_process_alone_finds_stops_every_process_naming_it(tmp_path):
    """Process 1 reads its share from its own copy of the scene (as on another host), where a target
    image of one of its views is broken; process 0's copy is whole, and it goes on until it meets
    the others. Process 1 stops on the file and tells the others (`distributed.announce_failure`):
    process 0 stops at the next barrier with the same file named and which process found it,
    instead of waiting there for a process that has left until JAX's timeouts (minutes)."""
    whole = write_tiny_scene(tmp_path / "whole")
    shutil.copytree(whole.parent, tmp_path / "copy")
    broken = tmp_path / "copy" / "targets" / "albedo" / "v1.png"      # view 1: share 1
    broken.write_bytes(broken.read_bytes()[:40])
    results = run_two([whole, tmp_path / "copy" / "scene.json"], tmp_path / "o", tmp_path / "cache", FLAGS,
                      timeout=120)
    (code0, log0), (code1, log1) = results
    assert code1 != 0 and str(broken) in log1 and "found by process" not in log1, log1[-3000:]
    assert code0 != 0 and str(broken) in log0 and "(found by process 1 of 2)" in log0, log0[-3000:]
    assert "Terminating process" not in log0 + log1            # JAX's fatal end when a peer vanishes


def test_announced_failures_are_raised_with_the_process_that_found_them():
    """What a process at a barrier raises for the failures others announced: their bad input as one
    InputError (each process's problems marked with it), else what stopped them."""
    problems = [("scene.json", "views[3].photo", "cannot read image")]
    entries = [(f"jaxdistill/failed/{q}", json.dumps({"problems": problems})) for q in (2, 1)]
    entries.append(("jaxdistill/failed/3", json.dumps({"error": "MemoryError: out of memory"})))
    read = []                                           # what the process tells the others it read

    class Client:
        def key_value_set(self, key, value):
            read.append(key)

    with pytest.raises(distributed.PeerInputError) as caught:
        distributed._raise_failures(Client(), entries)
    assert caught.value.problems == [("scene.json", "views[3].photo", "cannot read image (found by process 1 of 1)"),
                                     ("scene.json", "views[3].photo", "cannot read image (found by process 2 of 1)")]
    assert read == [f"jaxdistill/seen/{q}/0" for q in (1, 2, 3)]       # each failed process may now exit
    with pytest.raises(distributed.PeerFailed, match=r"process 3 of 1 stopped: MemoryError: out of memory \(its log"):
        distributed._raise_failures(Client(), entries[2:])
    distributed._raise_failures(Client(), [])           # nobody failed: nothing raised


def one_process(scene: Path, out: Path, **kw) -> dict:
    config = config_lib.validate(DistillConfig(scene=str(scene), out_dir=str(out), **{**FLAGS, **kw}))
    return pipeline.run(config, progress=False)


def test_two_processes_give_the_texels_of_one_and_process_0_writes_the_outputs(two_process_run, tmp_path,
                                                                                 monkeypatch):
    scene, out, logs = two_process_run
    assert "process 0 of 2: 1 local of 2 devices" in logs[0] and "process 1 of 2: 1 local of 2 devices" in logs[1]
    device = json.loads((out / "metrics.json").read_text())["device"]
    assert device["processes"] == 2 and len(device["devices"]) == 2
    assert (out / "scene.glb").is_file() and "outputs in" not in logs[1]        # only process 0 writes them
    # process 1 ray cast, planned and read the targets of its share alone (views 1 and 3 of 4)
    assert "process 1 holds 2 of the 4 views (share 1 of 2: v1, v3)" in logs[1] and "holds" not in logs[0]
    assert "fragments: 100%|██████████| 2/2" in logs[1] and "targets: 100%|██████████| 2/2" in logs[1]
    assert "fragments: 100%|██████████| 4/4" in logs[0]
    monkeypatch.setenv("JAXDISTILL_CACHE", str(tmp_path / "cache"))
    one_process(scene, tmp_path / "one", view_shares=2)
    two, one = texels(out), texels(tmp_path / "one")
    assert np.abs(one).max() > 0.1 and not np.array_equal(one, np.zeros_like(one))
    assert_close(two, one, rtol=1e-5)


def test_the_checkpoint_two_processes_wrote_resumes_in_one(two_process_run, tmp_path, monkeypatch):
    scene, out, _ = two_process_run
    monkeypatch.setenv("JAXDISTILL_CACHE", str(tmp_path / "cache"))
    resumed = tmp_path / "resumed"
    shutil.copytree(out, resumed)
    with pytest.raises(InputError, match=r"--view_shares: the checkpoint's steps drew their views from 2 share.*"
                                         r"in one process with --view_shares=2"):      # one share unless told
        one_process(scene, resumed, steps=STEPS + 2, resume=True)
    one_process(scene, resumed, steps=STEPS + 2, resume=True, view_shares=2)
    one_process(scene, tmp_path / "fresh", steps=STEPS + 2, view_shares=2)
    assert_close(texels(resumed), texels(tmp_path / "fresh"), rtol=1e-5)


@pytest.mark.parametrize("address,count,rank,flag,words", [
    ("", 2, -1, "num_processes", "--coordinator_address is empty"),
    ("", 1, 1, "process_id", "without --coordinator_address"),
    ("node001", 2, 0, "coordinator_address", "is not HOST:PORT"),
    ("node001:99999", 2, 0, "coordinator_address", "is not HOST:PORT"),
    ("node001:1234", 1, 0, "num_processes", "must be >= 2"),
    ("10.0.0.1:1234", 2, 2, "process_id", r"must be in \[0, 2\)"),
    ("10.0.0.1:1234", 2, -1, "process_id", r"must be in \[0, 2\)"),
])
def test_bad_multi_process_flags_are_named(tmp_path, address, count, rank, flag, words):
    with pytest.raises(InputError, match=rf"--{flag}.*{words}"):
        config_lib.validate(DistillConfig(scene=str(tmp_path / "s.json"), out_dir=str(tmp_path / "o"),
                                          coordinator_address=address, num_processes=count, process_id=rank))


def test_good_multi_process_flags_pass_and_rows_split_by_process():
    for address, count, rank in (("", 1, -1), ("auto", 1, -1), ("node001:1234", 4, 3), ("[::1]:8476", 2, 0)):
        assert distributed.address_problem(address, count, rank) == []
    import jax
    mesh = jax.sharding.Mesh(np.array(jax.devices()), ("data",))
    by_view = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
    assert distributed.local_rows(by_view, 8) == (0, 8)             # one process holds every row
    placed = distributed.place_batch(lambda ids: {"view": ids * 10}, np.arange(4), by_view)
    assert np.array_equal(np.asarray(placed["view"]), [0, 10, 20, 30])


def test_auto_outside_a_cluster_is_refused_naming_the_flag(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "OMPI_", "KUBERNETES_", "TPU_"))}
    env["JAX_PLATFORMS"] = "cpu"
    scene = write_tiny_scene(tmp_path / "scene")
    proc = subprocess.run([sys.executable, "-m", "jaxdistill.main", f"--scene={scene}", f"--out_dir={tmp_path / 'o'}",
                           "--prior=views", "--coordinator_address=auto"], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode != 0 and "--coordinator_address: auto found no cluster" in proc.stderr
    assert not (tmp_path / "o").exists()


def _problem_of(num_views: int, held=None) -> Problem:
    """A Problem with only what `view_ids` and `rows` read (a scene of `num_views` views, `held`)."""
    problem = Problem.__new__(Problem)
    object.__setattr__(problem, "scene", type("S", (), {"views": [None] * num_views})())
    object.__setattr__(problem, "held", held)
    return problem


def test_one_share_draws_as_runs_did_before_shares_and_shares_draw_evenly_from_each():
    problem = _problem_of(11)
    for step in range(20):
        before = np.random.default_rng([5, step]).choice(11, 4, replace=False)   # the sampler before shares
        assert np.array_equal(problem.view_ids(step, 4, 5), before)
        two = problem.view_ids(step, 4, 5, shares=2)
        assert np.array_equal(two, problem.view_ids(step, 4, 5, shares=2))        # a function of its arguments
        assert set(two[:2]) <= set(range(0, 11, 2)) and set(two[2:]) <= set(range(1, 11, 2))
        assert len(set(two.tolist())) == 4
    assert np.array_equal(distributed.view_share(11, 1, 3), [1, 4, 7, 10])
    drawn = np.concatenate([problem.view_ids(s, 6, 0, shares=3) for s in range(200)])
    assert set(drawn.tolist()) == set(range(11))                                  # every view gets drawn


def test_a_process_takes_the_rows_of_the_views_it_holds_and_names_those_it_does_not():
    problem = _problem_of(7, held=np.array([1, 4]))
    assert np.array_equal(problem.rows([4, 1, 4]), [1, 0, 1])
    with pytest.raises(ValueError, match=r"views \[2, 6\] are not among the 2 this process holds"):
        problem.rows([1, 2, 6])
    assert np.array_equal(_problem_of(7).rows([6, 0]), [6, 0])
    assert distributed.held_views(7) is None                       # one process holds every view
    made = {"a": np.arange(3)}
    assert distributed.from_primary(lambda: made) is made          # one process: its own arrays


@pytest.mark.parametrize("kw,words", [
    (dict(view_shares=-1), "must be >= 0"),
    (dict(view_shares=3, views_per_step=4), "do not split --views_per_step=4"),
    (dict(view_shares=3, views_per_step=6, coordinator_address="node001:1234", num_processes=2, process_id=0),
     "each of the --num_processes=2 processes holds one share"),
])
def test_bad_view_shares_are_named(tmp_path, kw, words):
    with pytest.raises(InputError, match=rf"--view_shares.*{words}"):
        config_lib.validate(DistillConfig(scene=str(tmp_path / "s.json"), out_dir=str(tmp_path / "o"), **kw))



@pytest.mark.parametrize("flags", [
    dict(),                                                                         # bilinear, the views prior
    dict(sampler="trilinear", texture_size="auto", photo_weight=0.5, render_size=16, view_data="disk"),
])
def test_a_share_built_alone_gives_the_batches_of_the_whole_build(tmp_path, monkeypatch, flags):
    """A process holding one share builds its views' per-view arrays alone from process 0's layout,
    needs and counts (here in one process: `held_views` patched to share 1 of 2 and `from_primary`
    to hand over, through a savez round trip of its own format, what a whole build sent). Its
    batches of its views equal the whole build's, every array bit for bit; a view of another share
    is refused."""
    import io

    from jaxdistill.engine import problem as problem_mod

    scene = write_tiny_scene(tmp_path / "scene", views=5, width=32, height=24)
    config = config_lib.validate(DistillConfig(scene=str(scene), out_dir=str(tmp_path / "o"), prior="views",
                                               views_per_step=2, **flags))
    sent = []

    def record(make):
        made = make()
        buffer = io.BytesIO()
        np.savez(buffer, **made)
        sent.append(buffer.getvalue())
        return made

    monkeypatch.setattr(jax, "process_count", lambda: 2)                # the primary packs its needs to send
    monkeypatch.setattr(distributed, "from_primary", record)
    whole = problem_mod.build_problem(config, cache_dir=tmp_path / "cache")
    assert len(sent) == 2 and whole.held is None

    replies = iter(sent)
    monkeypatch.setattr(distributed, "from_primary", lambda make: dict(np.load(io.BytesIO(next(replies)))))
    monkeypatch.setattr(distributed, "held_views", lambda n: distributed.view_share(n, 1, 2))
    share = problem_mod.build_problem(config, cache_dir=tmp_path / "cache2")
    assert np.array_equal(share.held, [1, 3]) and share.evidence is None
    assert share.space.num_texels == whole.space.num_texels and np.array_equal(share.counts, whole.counts)
    if flags:
        assert share.views_on_disk and share.photos is not None and share.space.layout.mipmaps
    for ids in ([1, 3], [3, 3]):
        mine, theirs = share.batch(np.array(ids)), whole.batch(np.array(ids))
        leaves = jax_tree.leaves_with_path(theirs)
        assert jax_tree.structure(mine) == jax_tree.structure(theirs) and len(leaves) >= (12 if flags else 7)
        for (path, a), b in zip(leaves, jax_tree.leaves(mine)):
            np.testing.assert_array_equal(np.asarray(b), np.asarray(a), err_msg=str(path))
    with pytest.raises(ValueError, match=r"views \[2\] are not among the 2 this process holds"):
        share.batch(np.array([1, 2]))
