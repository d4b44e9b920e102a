"""Per-view arrays on disk (--view_data): rows read back as written, the file nameless from the
start and gone with the array, the disk checked before compute, and a problem whose batches are
the same bit for bit wherever its images are held."""

from __future__ import annotations

import errno
import json
import os
import shutil
import time
from collections import namedtuple
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from jaxdistill.engine import config as config_lib
from jaxdistill.engine.config import DistillConfig
from jaxdistill.engine.problem import build_problem, view_data_bytes
from jaxdistill.errors import InputError
from jaxdistill.io import view_rows
from jaxdistill.io.view_rows import MapRows, SourceRows, ViewFolder, ViewRows, placement, view_array
from jaxdistill.render.fragments import ROW_FIELDS, FragmentRows, row_bytes_per_pixel
from jaxdistill.render.layout import page_footprints
from jaxdistill.scene.model import read_scene
from tiny_scene import write_tiny_scene


def test_rows_read_back_as_written_in_any_order(tmp_path):
    rng = np.random.default_rng(0)
    reference = rng.normal(size=(7, 5, 3, 2)).astype(np.float32)
    rows = ViewFolder(tmp_path).rows("targets", reference.shape, np.float32)
    for v in rng.permutation(7):
        rows[v] = reference[v]
    for ids in ([3], [0, 6, 6, 2], np.array([5, 1], np.int64), np.arange(7)):
        np.testing.assert_array_equal(rows[np.asarray(ids)], reference[np.asarray(ids)])
    np.testing.assert_array_equal(rows[4], reference[4])
    np.testing.assert_array_equal(rows[-1], reference[-1])
    assert rows[np.array([2, 3])].dtype == np.float32 and rows.shape == reference.shape and len(rows) == 7
    assert rows.nbytes == reference.nbytes
    rows[1] = reference[1].astype(np.float64) * 2          # cast to the array's dtype, as NumPy assigns
    np.testing.assert_array_equal(rows[1], (reference[1].astype(np.float64) * 2).astype(np.float32))
    with pytest.raises(IndexError):
        rows[np.array([7])]
    with pytest.raises(ValueError, match=r"a row of .* is \(5, 3, 2\)"):
        rows[0] = np.zeros((5, 3), np.float32)
    with pytest.raises(TypeError):
        rows[np.array([0.5])]


def test_the_file_has_no_name_and_its_space_goes_with_the_array(tmp_path):
    folder = ViewFolder(tmp_path)
    rows = folder.rows("photos", (3, 4, 4, 3), np.float32)
    rows[2] = np.ones((4, 4, 3), np.float32)
    assert list(folder.root.iterdir()) == []             # unlinked when opened: a killed run leaves nothing
    fd = rows._fd
    assert os.fstat(fd).st_size == rows.nbytes
    rows.close()
    with pytest.raises(OSError):
        os.fstat(fd)


def test_rows_refuse_what_they_cannot_hold_and_a_full_disk_is_named(tmp_path, monkeypatch):
    folder = ViewFolder(tmp_path)
    with pytest.raises(ValueError, match=r"rows of shape \(\) are not supported"):
        folder.rows("counts", (5,), np.float32)
    rows = folder.rows("targets", (2, 3), np.float32)
    rows.close()
    with pytest.raises(ValueError, match="is closed"):
        rows[0]

    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", full)
    with pytest.raises(InputError) as err:
        folder.rows("plan_index", (4, 1024, 4), np.int32)
    assert str(folder.root) in str(err.value) and "plan_index do not fit" in str(err.value)
    assert "--view_data=memory" in str(err.value)


def test_map_rows_hold_each_views_maps_in_a_file_per_map_and_read_a_map_when_asked(tmp_path, monkeypatch):
    """Per-view dicts of maps (the ground truth with --view_data on disk): the maps each view has,
    read back as written (a view without a map has none), a map's file taking every view's rows
    when first written, names known without a read, one map read when one is asked for."""
    rng = np.random.default_rng(2)
    folder = ViewFolder(tmp_path)
    rows = MapRows(folder, "gt", 3, (4, 5), {"albedo": 3, "roughness": 1, "irradiance": 3})
    views = [{"albedo": rng.random((4, 5, 3), np.float32), "roughness": rng.random((4, 5, 1), np.float32)},
             {},
             {"roughness": rng.random((4, 5, 1), np.float32)}]
    for v, maps in enumerate(views):
        rows[v] = maps
    assert len(rows) == 3 and folder.nbytes == 3 * 4 * 5 * (3 + 1) * 4          # no file for irradiance: no view has it
    assert list(folder.root.iterdir()) == []
    for v in (2, 0, 1, -1):
        got = rows[v]
        assert set(got) == set(views[v]) and len(got) == len(views[v])
        for m in views[v]:
            assert m in got and got[m].dtype == np.float32
            np.testing.assert_array_equal(got[m], views[v][m])
    assert "albedo" not in rows[2] and "irradiance" not in rows[0]
    with pytest.raises(KeyError):
        rows[2]["albedo"]
    with pytest.raises(IndexError):
        rows[3]
    reads = []
    real = ViewRows.__getitem__
    monkeypatch.setattr(ViewRows, "__getitem__", lambda self, ids: reads.append(self.path.name) or real(self, ids))
    assert sorted(rows[0]) == ["albedo", "roughness"] and not reads           # the names: no read
    rows[0]["roughness"]
    assert reads and all(name.startswith("gt_roughness") for name in reads)     # that map's file alone
    monkeypatch.undo()
    with pytest.raises(ValueError, match=r"maps \['normal'\] were not among"):
        rows[1] = {"normal": np.zeros((4, 5, 3), np.float32)}
    with pytest.raises(TypeError, match="float64"):
        rows[1] = {"albedo": np.zeros((4, 5, 3))}


def test_seam_pairs_are_held_as_two_bits_a_pixel_and_read_back_from_a_file(tmp_path):
    """The evaluation's seam pairs as packed edges (`scoring.SeamPairs`): from a list or a
    `ViewRows` file, in any order and from two threads at once, the pairs `metrics.seam_pairs`
    gives; a list of views of two other sizes (bits padded to whole bytes); the file takes two bits a
    pixel, whatever the pairs."""
    from jaxdistill.evaluate import metrics, scoring

    rng = np.random.default_rng(0)
    shapes = [(7, 9), (7, 9), (7, 9), (7, 9)]
    views = [(rng.integers(0, k, s), rng.integers(0, 2, s), rng.random(s) > 0.1) for k, s in zip((3, 1, 5, 2), shapes)]
    pairs = [metrics.seam_pairs(*view) for view in views]
    assert [len(a) for a, _ in pairs][1] == 0 and sum(len(a) for a, _ in pairs) > 0
    folder = ViewFolder(tmp_path)
    rows = folder.rows("seams", (4, metrics.seam_edge_bytes(7, 9)), np.uint8)
    listed = []
    for v, view in enumerate(views):
        rows[v] = metrics.pack_seam_edges(metrics.seam_edges(*view))
        listed.append(metrics.pack_seam_edges(metrics.seam_edges(*view)))
    assert folder.nbytes == os.fstat(rows._fd).st_size == 4 * -(-2 * 7 * 9 // 8)
    for seams in (scoring.SeamPairs(rows, shapes), scoring.SeamPairs(listed, shapes)):
        assert len(seams) == 4
        for v in (2, 0, 3, 1, -1):
            for got, want in zip(seams[v], pairs[v], strict=True):
                assert got.dtype == np.int32
                np.testing.assert_array_equal(got, want)
        with ThreadPoolExecutor(2) as pool:
            for got, v in zip(pool.map(seams.__getitem__, [2, 0, 2, 3] * 8), [2, 0, 2, 3] * 8):
                for x, y in zip(got, pairs[v], strict=True):
                    np.testing.assert_array_equal(x, y)
        with pytest.raises(IndexError):
            seams[4]
    odd = [(rng.integers(0, 3, s), np.zeros(s, int)) for s in ((3, 5), (6, 2))]     # 30 bits (2 padding) and 24
    seams = scoring.SeamPairs([metrics.pack_seam_edges(metrics.seam_edges(*o)) for o in odd], [(3, 5), (6, 2)])
    for v, o in enumerate(odd):
        for got, want in zip(seams[v], metrics.seam_pairs(*o), strict=True):
            np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="2 views' shapes"):
        scoring.SeamPairs(listed, shapes[:2])
    rows.close()
    with pytest.raises(ValueError, match="is closed"):
        scoring.SeamPairs(rows, shapes)[0]


def test_source_rows_read_the_files_again_and_refuse_one_changed_since(tmp_path):
    """`SourceRows` reads a view's row from its files when asked for, and names a file that changed
    (or went) after the array was made instead of reading another image."""
    from jaxdistill.io import images as imageio

    rng = np.random.default_rng(0)
    paths = [tmp_path / f"view_{v}.png" for v in range(3)]
    for path in paths:
        imageio.write_image(path, rng.uniform(size=(5, 7, 3)).astype(np.float32))
    expected = np.stack([imageio.read_image(p) for p in paths])
    rows = SourceRows((3, 5, 7, 3), np.float32, lambda v: imageio.read_image(paths[v]), [[p] for p in paths],
                      name="targets")
    assert rows.nbytes == 0 and len(rows) == 3 and rows.ndim == 4
    np.testing.assert_array_equal(rows[np.array([2, 0, 2])], expected[[2, 0, 2]])
    np.testing.assert_array_equal(rows[1], expected[1])
    with pytest.raises(IndexError):
        rows[np.array([3])]
    imageio.write_image(paths[1], rng.uniform(size=(5, 7, 3)).astype(np.float32))
    os.utime(paths[1], ns=(time.time_ns(), time.time_ns() + 10 ** 9))     # a new time whatever the clock's grain
    np.testing.assert_array_equal(rows[np.array([0])], expected[[0]])     # the others still read
    for gone in (False, True):
        if gone:
            paths[1].unlink()
        with pytest.raises(InputError) as err:
            rows[np.array([0, 1])]
        assert str(paths[1]) in str(err.value) and "targets" in str(err.value) and "changed" in str(err.value)


def test_view_array_is_numpy_in_memory_and_rows_on_disk(tmp_path):
    memory = view_array("t", (2, 3), np.float32, None)
    assert isinstance(memory, np.ndarray) and not memory.any()
    disk = view_array("t", (2, 3), np.float32, ViewFolder(tmp_path))
    assert isinstance(disk, ViewRows)
    np.testing.assert_array_equal(disk[np.arange(2)], memory)    # a new file reads as zeros, like np.zeros


def test_placement_follows_the_flag_and_auto_the_size():
    assert not placement("memory", 1 << 40) and placement("disk", 1)
    assert not placement("auto", view_rows.AUTO_DISK_BYTES) and placement("auto", view_rows.AUTO_DISK_BYTES + 1)
    with pytest.raises(ValueError):
        placement("ssd", 1)
    with pytest.raises(InputError, match=r"--view_data: must be one of auto, memory, disk, got 'ssd'"):
        config_lib.validate(DistillConfig(scene="s", out_dir="o", view_data="ssd"))


def test_files_that_would_not_fit_are_refused_naming_the_folder(tmp_path, monkeypatch):
    usage = namedtuple("usage", "total used free")
    need = 10 << 20
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(1 << 40, 0, need + view_rows.DISK_HEADROOM - 1))
    folder = ViewFolder(tmp_path / "cache")
    with pytest.raises(InputError) as err:
        folder.check_space(need, "the per-view images of 3 views")
    message = str(err.value)
    assert str(tmp_path / "cache" / "view_rows") in message and "the per-view images of 3 views need 0.01 GB" in message
    assert "--view_data=memory" in message and "$JAXDISTILL_CACHE" in message
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(1 << 40, 0, need + view_rows.DISK_HEADROOM))
    folder.check_space(need, "the per-view images of 3 views")


def test_the_set_up_fits_its_files_to_the_disk_before_any_cast(tmp_path, monkeypatch, caplog):
    """Per-view files that would not fit are refused before any ray is cast, naming the folder;
    where float32 copies of the targets would not fit and the targets' own files (at the render
    size) can be read again instead, they are, with a warning; ray casts that would not fit beside
    the files are cast and not kept (a warning says how much and where), and cached where they fit."""
    from jaxdistill.render import fragments as fr

    scene = write_tiny_scene(tmp_path / "scene", views=2)
    config = config_lib.validate(DistillConfig(scene=str(scene), out_dir=str(tmp_path / "out"), steps=2,
                                               views_per_step=2, prior="views", view_data="disk"))
    views = read_scene(scene.parent)
    cameras = [v.camera for v in views.views]
    casts = sum(c.height * c.width * fr.CACHE_BYTES_PER_PIXEL + fr.CACHE_BYTES_PER_VIEW for c in cameras)
    # what the check counts: each distinct view's ray cast once, none once they are cached
    assert fr.uncached_bytes(views.mesh, cameras + cameras, tmp_path / "cache") == casts
    assert fr.uncached_bytes(views.mesh, cameras, False) == 0
    problem = build_problem(config, cache_dir=tmp_path / "unlimited")
    assert isinstance(problem.prior.target_images, ViewRows)             # copies where they fit
    # the set-up's own files and the evaluation context's, which it makes later, with and without the copies
    args = (config, problem.scene, problem.choice, problem.channels, (problem.height, problem.width))
    copies, sourced = view_data_bytes(*args), view_data_bytes(*args, form="sources")
    assert copies - sourced == 2 * problem.height * problem.width * 4 * 11 > casts
    assert copies > problem.view_folder.nbytes > 0
    assert len(list((tmp_path / "unlimited" / "fragments").glob("*.npz"))) == 2
    cached = tmp_path / "unlimited" / "fragments" / f"{fr.view_key(fr.mesh_key(views.mesh), cameras[0])}.npz"
    cached.unlink()                                           # one of the two cached: the other is counted
    assert fr.uncached_cameras(views.mesh, cameras + cameras, tmp_path / "unlimited") == [cameras[0]]
    assert fr.uncached_bytes(views.mesh, cameras, tmp_path / "unlimited") == fr.cast_bytes(cameras[:1]) < casts
    del problem
    usage = namedtuple("usage", "total used free")

    def free(nbytes):
        monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(1 << 40, 0, nbytes))

    def poisoned(*args, **kwargs):
        raise AssertionError("rays were cast before the disk space was checked")

    real_cast = fr.cast_view
    monkeypatch.setattr(fr, "cast_view", poisoned)
    free(sourced + view_rows.DISK_HEADROOM - 1)
    with pytest.raises(InputError) as err:
        build_problem(config, cache_dir=tmp_path / "cache")
    message = str(err.value)
    assert f"the per-view arrays of 2 views (--view_data=disk) need {sourced / 2 ** 30:.2f} GB" in message
    assert str(tmp_path / "cache" / "view_rows") in message
    monkeypatch.setattr(fr, "cast_view", real_cast)
    free(sourced + casts + view_rows.DISK_HEADROOM - 1)       # the files fit without the copies, the casts not
    with caplog.at_level("WARNING"):
        problem = build_problem(config, cache_dir=tmp_path / "cache")
    assert isinstance(problem.prior.target_images, SourceRows)
    assert not list((tmp_path / "cache" / "fragments").glob("*.npz"))
    messages = [r.getMessage() for r in caplog.records]
    assert any("read again from the scene's files" in m and str(tmp_path / "cache" / "view_rows") in m
               for m in messages)
    assert any("the ray casts are not cached: those of 2 views" in m and f"{casts / 2 ** 30:.2f} GB" in m
               and str(tmp_path / "cache" / "fragments") in m for m in messages)
    del problem
    free(copies + casts + view_rows.DISK_HEADROOM)           # everything fits: copies, and the casts cached
    problem = build_problem(config, cache_dir=tmp_path / "cache")
    assert isinstance(problem.prior.target_images, ViewRows)
    assert len(list((tmp_path / "cache" / "fragments").glob("*.npz"))) == 2


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return write_tiny_scene(tmp_path_factory.mktemp("view_rows"), views=4)


@pytest.mark.parametrize("terms", [dict(), dict(photo_weight=1.0, albedo_smoothness=0.1, photo_size=24),
                                   dict(photo_weight=1.0, albedo_smoothness=0.1, photo_size=32, render_size=32)],
                         ids=["targets", "photos", "the files' size"])
def test_a_problem_on_disk_reads_the_batches_and_scores_of_one_in_memory(tiny_scene, tmp_path, terms, monkeypatch):
    """Every per-view array (fragments, plans, pixel weights, targets, photos, guides), and the
    evaluation's fragments and plans at the photos' size, are files with --view_data=disk, but
    targets and photos that are their files' pixels (no resampling) on a disk too small for their
    copies, which are read again from those files; the batches and the evaluation (its renders, seams and masks) are those of
    --view_data=memory bit for bit."""
    from jaxdistill.evaluate import ground_truth as evaluation, scoring

    def problem(view_data):
        config = config_lib.validate(DistillConfig(scene=str(tiny_scene), out_dir=str(tmp_path / view_data), steps=2,
                                                   views_per_step=2, prior="views", view_data=view_data,
                                                   **{"render_size": 16, **terms}))
        built = build_problem(config, cache_dir=tmp_path / "cache")
        return built, scoring.evaluation_context(config, built), config

    memory, memory_ctx, _ = problem("memory")
    # the scene's files are 32 x 24: at that size, on a disk too small for float32 copies of targets and
    # photos, they are read again from those files; resampled ones always go into files
    at_files_size = terms.get("render_size") == 32
    if at_files_size:
        usage = namedtuple("usage", "total used free")
        config = config_lib.validate(DistillConfig(scene=str(tiny_scene), out_dir=str(tmp_path), prior="views",
                                                   **terms))
        args = (config, memory.scene, memory.choice, memory.channels, (memory.height, memory.width))
        assert view_data_bytes(*args, form="sources") < view_data_bytes(*args)
        monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(1 << 40, 0, view_data_bytes(*args)
                                                                           + view_rows.DISK_HEADROOM - 1))
    disk, disk_ctx, config = problem("disk")
    on_disk = [disk.plan_index, disk.plan_weight, disk.plan_hit, disk.pixel_weight,
               disk_ctx.plan.index, disk_ctx.plan.weight, disk_ctx.plan.hit, disk_ctx.masks]
    assert all(isinstance(a, ViewRows) for a in on_disk)
    assert isinstance(disk.prior.target_images, SourceRows if at_files_size else ViewRows)
    assert isinstance(memory.plan_index, np.ndarray) and isinstance(memory.prior.target_images, np.ndarray)
    assert isinstance(memory.fragments, list) and isinstance(disk.fragments, FragmentRows)
    assert all(isinstance(a, ViewRows) for a in disk.fragments.arrays.values())
    # no barycentric, depth, object (the mesh's of the triangle) or uv_grad (the bilinear sampler's plans need none)
    assert sorted(disk.fragments.arrays) == sorted(ROW_FIELDS) == ["triangle", "uv"]
    assert row_bytes_per_pixel() == 12 and row_bytes_per_pixel(uv_grad=True) == 28
    for frags in ("fragments", "native_fragments"):
        for one, other in zip(getattr(memory, frags), getattr(disk, frags), strict=True):
            assert other.barycentric is None and other.depth is None and other.uv_grad is None
            assert one.depth is not None and one.uv_grad is not None
            for name in ROW_FIELDS + ("object_id",):
                assert getattr(one, name).dtype == getattr(other, name).dtype
                np.testing.assert_array_equal(getattr(one, name), getattr(other, name), err_msg=name)
    # the page sizes came from the footprints taken as the fragments were made: the layout of memory's
    assert memory.space.layout.page_sizes == disk.space.layout.page_sizes
    np.testing.assert_array_equal(disk.fragments.footprints,
                                  [page_footprints(f, disk.space.layout.object_page, disk.space.layout.num_pages)
                                   for f in memory.fragments])
    if terms:
        assert all(isinstance(a, ViewRows) for a in (disk.photos.guide, disk.photos.index, disk.photos.hit,
                                                     disk.photos.pixel_weight))
        assert isinstance(disk.photos.photos, SourceRows if at_files_size else ViewRows)
    # what the set-up checked against the free space before any compute is what the files took, to the byte,
    # the evaluation's seam pairs included (two bits a pixel, whatever the seams)
    checked = view_data_bytes(config, disk.scene, disk.choice, disk.channels, (disk.height, disk.width),
                              form="sources" if at_files_size else "copies")
    assert checked == disk.view_folder.nbytes > 0
    for ids in ([0, 1], [3, 3], [2, 0]):
        a, b = memory.batch(np.array(ids)), disk.batch(np.array(ids))
        assert a.keys() == b.keys() and ("photo" in a) == bool(terms)
        for name in a:
            np.testing.assert_array_equal(np.asarray(a[name]) if name != "prior" else a[name]["target"],
                                          np.asarray(b[name]) if name != "prior" else b[name]["target"], err_msg=name)
    np.testing.assert_array_equal(memory.counts, disk.counts)
    np.testing.assert_array_equal(memory.evidence, disk.evidence)
    texels = np.random.default_rng(1).uniform(-1, 1, (memory.space.num_texels, memory.channels.num_channels))
    renders = [evaluation.render_views(texels, c.plan, c.cameras, memory.channels) for c in (memory_ctx, disk_ctx)]
    for one, other in zip(*renders):
        for m in one:
            np.testing.assert_array_equal(one[m], other[m])
    assert isinstance(disk_ctx.seams.packed, ViewRows) and isinstance(memory_ctx.seams.packed, list)
    # the ground-truth maps (gt.json's albedo, roughness, metallic and geometry normals) in files, the same values
    assert isinstance(disk_ctx.gt_maps, MapRows) and isinstance(memory_ctx.gt_maps, list)
    assert set(disk_ctx.gt_maps.rows) == {"albedo", "roughness", "metallic", "normal"}
    for one, other in zip(memory_ctx.gt_maps, disk_ctx.gt_maps, strict=True):
        assert set(one) == set(other)
        for m in one:
            assert other[m].dtype == one[m].dtype
            np.testing.assert_array_equal(one[m], other[m], err_msg=m)
    assert isinstance(memory_ctx.masks, list) and sum(m.sum() for m in memory_ctx.masks) > 0
    for one, other in zip(memory_ctx.masks, disk_ctx.masks, strict=True):
        np.testing.assert_array_equal(one, other)
    for one, other in zip(memory_ctx.plan.hit_images(), disk_ctx.plan.hit_images(), strict=True):
        np.testing.assert_array_equal(one, other)
    assert sum(len(a) for a, _ in memory_ctx.seams) > 0
    for one, other in zip(memory_ctx.seams, disk_ctx.seams, strict=True):
        for x, y in zip(one, other, strict=True):
            assert x.dtype == y.dtype
            np.testing.assert_array_equal(x, y)


def test_a_run_with_its_per_view_arrays_on_disk_writes_what_one_in_memory_writes(tiny_scene, tmp_path, monkeypatch):
    """The main job end to end, --view_data=memory and =disk (baselines and renders then lazy):
    the same scores and re-rendering figures, and the same map and evidence pages and renders bit
    for bit. On disk the photos' re-rendering walks the lazy renders after the scores have (they
    keep one chunk for all threads: walked at once, each would render the other's chunks again);
    in memory beside them."""
    from jaxdistill import pipeline
    from jaxdistill.export import outputs
    from jaxdistill.io import images as imageio

    events = []
    score, rerender = outputs.scoring.score, outputs.rerender_scores

    def scored(*args):
        out = score(*args)
        time.sleep(0.5)                       # slow scores: without the wait, the re-rendering would start first
        events.append("scored")
        return out

    monkeypatch.setattr(outputs.scoring, "score", scored)
    monkeypatch.setattr(outputs, "rerender_scores", lambda *args: events.append("rerender") or rerender(*args))

    def run(view_data):
        events.clear()
        config = config_lib.validate(DistillConfig(scene=str(tiny_scene), out_dir=str(tmp_path / view_data), steps=3,
                                                   views_per_step=2, prior="views", view_data=view_data,
                                                   photo_weight=1.0, render_size=16, contact_views=2))
        return pipeline.run(config, progress=False), list(events)

    (memory, _), (disk, order) = run("memory"), run("disk")
    assert order == ["scored", "rerender"]
    assert memory["view_data"]["where"] == "memory" and disk["view_data"]["where"] == "disk"
    assert disk["view_data"]["disk_bytes"] > 0 and memory["view_data"]["disk_bytes"] == 0
    for key in ("ours", "baseline_per_view_estimates", "improvement", "rerender"):     # NaN where nothing to score
        assert json.dumps(memory[key], sort_keys=True) == json.dumps(disk[key], sort_keys=True), key
    pages = sorted(p.relative_to(tmp_path / "memory") for folder in ("maps", "evidence")
                   for p in (tmp_path / "memory" / folder).rglob("*.exr"))
    assert any(p.parts[0] == "evidence" for p in pages) and any(p.parts[0] == "maps" for p in pages)
    for page in pages:
        np.testing.assert_array_equal(imageio.read_image(tmp_path / "memory" / page),
                                      imageio.read_image(tmp_path / "disk" / page))
    renders = sorted(p.relative_to(tmp_path / "memory") for p in (tmp_path / "memory" / "renders").rglob("*.png"))
    assert len(renders) == len(list((tmp_path / "disk" / "renders").rglob("*.png"))) > 0
    for render in renders:                          # rendered a chunk at a time when asked for: the same pixels
        np.testing.assert_array_equal(imageio.read_image(tmp_path / "memory" / render),
                                      imageio.read_image(tmp_path / "disk" / render))


@pytest.mark.parametrize("gt_json", [True, False], ids=["gt_json_and_images", "images_only"])
def test_ground_truth_from_gt_json_and_some_views_images_reads_back_from_files_as_held_in_memory(tmp_path, gt_json):
    """Views' ground_truth images on views 0 and 2 only, with and without gt.json: on disk the same
    maps per view as in memory (views 1 and 3 without any when gt.json is absent), the same scores,
    and the disk check's size that of the files written."""
    from jaxdistill.evaluate import ground_truth as evaluation, scoring

    path = write_tiny_scene(tmp_path / "scene", views=4, gt=gt_json)
    doc = json.loads(path.read_text())
    for i in (0, 2):
        doc["views"][i]["ground_truth"] = {"irradiance": f"targets/irradiance/v{i}.png",
                                           "albedo": f"targets/albedo/v{i}.png"}
    path.write_text(json.dumps(doc))
    built = {}
    for view_data in ("memory", "disk"):
        config = config_lib.validate(DistillConfig(scene=str(path), out_dir=str(tmp_path / view_data), steps=2,
                                                   views_per_step=2, prior="views", view_data=view_data,
                                                   render_size=16))
        problem = build_problem(config, cache_dir=tmp_path / "cache")
        built[view_data] = (problem, scoring.evaluation_context(config, problem), config)
    (_, memory, _), (disk_problem, disk, config) = built["memory"], built["disk"]
    assert isinstance(disk.gt_maps, MapRows) and isinstance(memory.gt_maps, list)
    names = [sorted(g) for g in disk.gt_maps]
    if gt_json:
        assert names[0] == ["albedo", "irradiance", "metallic", "normal", "roughness"] == names[2]
        assert names[1] == ["albedo", "metallic", "normal", "roughness"] == names[3]
    else:
        assert names == [["albedo", "irradiance"], [], ["albedo", "irradiance"], []]
    for one, other in zip(memory.gt_maps, disk.gt_maps, strict=True):
        assert sorted(one) == sorted(other)
        for m in one:
            np.testing.assert_array_equal(one[m], other[m], err_msg=m)
    checked = view_data_bytes(config, disk_problem.scene, disk_problem.choice, disk_problem.channels,
                              (disk_problem.height, disk_problem.width))
    assert checked == disk_problem.view_folder.nbytes
    pred = [{"albedo": np.full(s + (3,), 0.4, np.float32), "irradiance": np.full(s + (3,), 0.7, np.float32)}
            for s in memory.shapes]
    a = evaluation.evaluate(pred, memory.gt_maps, memory.masks, memory.seams)
    b = evaluation.evaluate(pred, disk.gt_maps, disk.masks, disk.seams)
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True) and "albedo_psnr" in a
