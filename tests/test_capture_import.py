"""Your own capture, end to end: the dataset flags of the main job, of `jaxdistill import` and of
estimate and precompute (every loader's mesh problem names a flag the command that printed it has), and imports that
place the capture's files inside the scene folder (hard links, copies, symlinks, or none)."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import pytest
from absl import flags

import dataset_fixtures as fx
from dataset_fixtures import cache, cams  # noqa: F401  (fixtures)
from jaxdistill import estimate, import_scene, precompute
from jaxdistill.engine import config as config_lib
from jaxdistill.errors import InputError
from jaxdistill.scene.model import save_mesh

FLAG = re.compile(r"(?<![\w-])--([a-z][a-z0-9_]*)")


def main_flag_values() -> flags.FlagValues:
    """The main job's flags, as `python -m jaxdistill.main` declares them."""
    from jaxdistill import main

    fv = flags.FlagValues()
    config_lib.define_flags(fv)
    main.define_config_flag(fv)
    main.define_view_flags(fv)
    return fv


def import_flag_names() -> set[str]:
    return {s[2:] for action in import_scene.build_parser()._actions for s in action.option_strings
            if s.startswith("--")}


def run_main_job(scene: str, out: Path, *extra: str) -> InputError | None:
    """The main job's option path (flags -> DistillConfig -> build_problem -> loader) up to the
    scene read; the InputError it stops with, or None."""
    from jaxdistill.engine.problem import build_problem

    fv = main_flag_values()
    fv(["main", f"--scene={scene}", f"--out_dir={out}", "--prior=views", "--maps=albedo", *extra])
    try:
        build_problem(config_lib.config_from_flags(fv))
    except InputError as err:
        return err
    return None


def command_flag_values(command) -> flags.FlagValues:
    """The flags of `python -m jaxdistill.estimate` or `.precompute` (`command`), as it declares them."""
    fv = flags.FlagValues()
    command.define_flags(fv)
    return fv


def run_command(command, scene: str, out: Path, *extra: str) -> InputError | None:
    """estimate's or precompute's option path (flags -> config -> the scene read); the InputError
    it stops with, or None (estimate stops before loading a model, precompute after its run)."""
    fv = command_flag_values(command)
    fv([command.__name__, f"--scene={scene}", f"--out_dir={out}", "--prior_dir=unused", *extra]
       if command is estimate else [command.__name__, f"--scene={scene}", f"--out_dir={out}", *extra])
    try:
        if command is estimate:
            estimate.photos_to_estimate(estimate.config_from_flags(fv))
        else:
            precompute.run(precompute.config_from_flags(fv))
    except InputError as err:
        return err
    return None


def run_import(fmt: str, path: Path, out: Path, *extra: str, capsys) -> tuple[int, str, str]:
    code = import_scene.main([f"--format={fmt}", f"--path={path}", f"--out={out}", "--quiet", *extra])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def far_mesh(path: Path) -> Path:
    """The room moved 1000 units away: no camera sees it."""
    mesh = fx.room_mesh()
    save_mesh(dataclasses.replace(mesh, vertices=mesh.vertices + 1000.0), path)
    return path


def outside_config(folder: Path, mesh: Path) -> Path:
    """A scene config whose one object file lies outside its folder."""
    folder.mkdir(parents=True)
    doc = {"format": "jaxdistill-scene-config", "version": 1,
           "meshes": [{"name": "room", "file": f"../{mesh.parent.name}/{mesh.name}"}]}
    (folder / "objects.json").write_text(json.dumps(doc))
    return folder / "objects.json"


def mesh_problems(tmp_path, cams) -> list[tuple[str, Path, tuple[str, ...], str]]:
    """(format, dataset, flags, expected text) of each loader's mesh problems."""
    room = fx.write_mesh(tmp_path / "meshes" / "room.glb")
    far = far_mesh(tmp_path / "meshes" / "far.glb")
    config = outside_config(tmp_path / "config", room)
    data = {"fipt": fx.write_fipt(tmp_path / "fipt", cams), "iris": fx.write_fipt(tmp_path / "iris", cams, ldr=True),
            "scannetpp": fx.write_scannetpp(tmp_path / "spp", cams),
            "nerfstudio": fx.write_nerfstudio(tmp_path / "ns", cams), "colmap": fx.write_colmap(tmp_path / "colmap", cams)}
    cases = [(fmt, path, (f"--mesh={far}",), "no view sees") for fmt, path in data.items()]
    cases += [(fmt, path, (f"--mesh={config}",), "resolves outside") for fmt, path in data.items()]
    cases += [(fmt, data[fmt], (), "no mesh of its own") for fmt in ("nerfstudio", "colmap")]
    return cases


def test_every_loaders_mesh_problem_names_flags_of_the_command_that_printed_it(tmp_path, cams, capsys):
    main_flags = set(main_flag_values())
    import_flags = import_flag_names()
    for i, (fmt, path, extra, expected) in enumerate(mesh_problems(tmp_path, cams)):
        err = run_main_job(f"{fmt}:{path}", tmp_path / f"run{i}", *extra)
        assert err is not None and expected in str(err), (fmt, extra, err)
        named = set(FLAG.findall(str(err)))
        assert named and named <= main_flags, (fmt, extra, named - main_flags, str(err))
        code, _, stderr = run_import(fmt, path, tmp_path / f"imported{i}", *extra, capsys=capsys)
        assert code == 2 and expected in stderr, (fmt, extra, stderr)
        named = set(FLAG.findall(stderr))
        assert named and named <= import_flags, (fmt, extra, named - import_flags, stderr)
        for command in (estimate, precompute):
            err = run_command(command, f"{fmt}:{path}", tmp_path / f"{command.__name__}{i}", *extra)
            assert err is not None and expected in str(err), (command.__name__, fmt, extra, err)
            named, declared = set(FLAG.findall(str(err))), set(command_flag_values(command))
            assert named and named <= declared, (command.__name__, fmt, extra, named - declared, str(err))


def test_the_main_job_has_every_import_option_of_the_import_command():
    main_flags, import_flags = set(main_flag_values()), import_flag_names()
    carried = {f.name for f in dataclasses.fields(config_lib.ImportOptions)}
    assert set(config_lib.IMPORT_FLAGS) | {"allow_outside_paths"} == carried & import_flags
    assert set(config_lib.IMPORT_FLAGS) <= main_flags
    defaults = config_lib.DistillConfig(scene="", out_dir="")
    for name in config_lib.IMPORT_FLAGS:              # the same defaults in both commands
        assert getattr(defaults, name) == getattr(config_lib.ImportOptions(), name), name
        assert main_flag_values()[name].default == import_scene.build_parser().get_default(name), name
        for command in (estimate, precompute):
            assert command_flag_values(command)[name].default == main_flag_values()[name].default, name


def test_estimate_and_precompute_pass_the_dataset_flags_to_the_loader(tmp_path, cams):
    mesh = fx.write_mesh(tmp_path / "room.glb")
    capture = f"nerfstudio:{fx.write_nerfstudio(tmp_path / 'ns', cams)}"
    fv = command_flag_values(estimate)
    fv(["estimate", f"--scene={capture}", f"--out_dir={tmp_path / 'est'}", "--prior_dir=unused", f"--mesh={mesh}",
        "--max_views=2", "--exposure=1.5"])
    config = estimate.config_from_flags(fv)
    assert (config.dataset.mesh, config.dataset.max_views, config.dataset.exposure) == (str(mesh), 2, 1.5)
    photos = estimate.photos_to_estimate(config)
    assert len(photos) == 2 and {stops for _, _, stops in photos} == {1.5}
    summary = precompute.run(precompute.config_from_flags(command_flag_values_of(
        precompute, ["precompute", f"--scene={capture}", f"--out_dir={tmp_path / 'pre'}", f"--mesh={mesh}",
                     "--max_views=2", "--texture_size=16"])))
    assert summary["views"] == 2
    for command, extra in ((estimate, ["--prior_dir=unused"]), (precompute, [])):
        fv = command_flag_values_of(command, [command.__name__, "--scene=bedroom", f"--out_dir={tmp_path / 'x'}",
                                              f"--mesh={mesh}", *extra])
        with pytest.raises(InputError, match=r"--mesh: --mesh applies to --scene=FORMAT:PATH"):
            command.config_from_flags(fv)
        fv = command_flag_values_of(command, [command.__name__, f"--scene={capture}", f"--out_dir={tmp_path / 'x'}",
                                              "--max_views=-1", *extra])
        with pytest.raises(InputError, match=r"flags: --max_views: must be >= 0"):
            command.config_from_flags(fv)


def command_flag_values_of(command, argv: list[str]) -> flags.FlagValues:
    """`command_flag_values` parsed from `argv`."""
    fv = command_flag_values(command)
    fv(argv)
    return fv


def test_dataset_flags_reach_the_loader_and_are_refused_for_a_scene_folder(tmp_path, cams):
    from jaxdistill.engine.problem import build_problem

    mesh = fx.write_mesh(tmp_path / "room.glb")
    fv = main_flag_values()
    fv(["main", f"--scene=nerfstudio:{fx.write_nerfstudio(tmp_path / 'ns', cams)}", f"--out_dir={tmp_path / 'run'}",
        "--prior=views", "--maps=albedo", f"--mesh={mesh}", "--max_views=2", "--exposure=1.5"])
    config = config_lib.config_from_flags(fv)
    options = config_lib.import_options(config.as_dict())
    assert (options.mesh, options.max_views, options.exposure) == (str(mesh), 2, 1.5)
    with pytest.raises(InputError, match=r"has no albedo target"):       # read with the mesh: the views prior
        build_problem(config)                                           # then asks for its targets
    with pytest.raises(InputError, match=r"--mesh: --mesh, --exposure apply to --scene=FORMAT:PATH"):
        config_lib.validate(dataclasses.replace(config, scene="bedroom"))
    assert config_lib.validate(dataclasses.replace(config, scene="bedroom", mesh=None, exposure="auto")).max_views == 2
    with pytest.raises(InputError, match=r"flags: --uv: unknown policy 'bad'"):
        config_lib.validate(dataclasses.replace(config, uv="bad"))


# ----------------------------------------------------------------------------- self-contained imports

def capture(fmt: str, root: Path, cams) -> tuple[Path, tuple[str, ...]]:
    """(a tiny capture of `fmt`, the import flags it needs beyond format, path and out)."""
    mesh = fx.write_mesh(root / "meshes" / "room.ply")
    path = fx.write_nerfstudio(root / "ns", cams) if fmt == "nerfstudio" else fx.write_colmap(root / "colmap", cams)
    return path, (f"--mesh={mesh}",)


def photo_pairs(out: Path, path: Path):
    """(photo in the scene folder, the capture's photo) per view of the scene at `out`."""
    from jaxdistill.scene.model import read_scene

    scene = read_scene(out, allow_outside_paths=True, check_pixels=False)
    sources = {p.stem: p for p in path.parent.rglob("*.png") if "meshes" not in p.parts}
    return [(v.photo, sources[v.photo.stem]) for v in scene.views]


@pytest.mark.parametrize("fmt", ["nerfstudio", "colmap"])
def test_a_default_import_is_self_contained_runs_in_the_main_job_and_moves(fmt, tmp_path, cams, run_rgbx_dir, capsys):
    import shutil

    from jaxdistill import pipeline
    from jaxdistill.scene.model import read_scene

    path, extra = capture(fmt, tmp_path / "capture", cams)
    out = tmp_path / "scenes" / "room"
    code, stdout, stderr = run_import(fmt, path, out, *extra, capsys=capsys)
    assert code == 0, stderr
    assert f"files: 3 placed in {out} (--link=hardlink): 3 hard links; 0 bytes copied" in stdout
    assert "--allow_outside_paths" not in stdout and "note:" not in stdout
    assert json.loads((out / "import.json").read_text())["files"]["linked"] == 3
    for inside, source in photo_pairs(out, path):     # one file, two names (tmp_path is one device)
        assert inside.parent == out / "photos" and inside.stat().st_ino == source.stat().st_ino
    assert len(read_scene(out).views) == 3             # no --allow_outside_paths
    moved = tmp_path / "elsewhere" / "room"
    moved.parent.mkdir()
    shutil.move(out, moved)
    config = config_lib.validate(config_lib.DistillConfig(
        scene=str(moved), out_dir=str(tmp_path / "run"), steps=2, views_per_step=1, prior="rgbx",
        rgbx_dir=str(run_rgbx_dir), maps=("albedo",), renders=False, contact_views=1, estimate_steps=4))
    assert config.allow_outside_paths is False
    summary = pipeline.run(config, progress=False)
    assert summary["steps"] == 2 and (tmp_path / "run" / "metrics.json").is_file()


def test_link_copy_writes_copies_and_symlinks_need_the_outside_flag(tmp_path, cams, capsys):
    from jaxdistill.scene.model import read_scene

    path, extra = capture("nerfstudio", tmp_path / "capture", cams)
    copies = tmp_path / "copies"
    code, stdout, stderr = run_import("nerfstudio", path, copies, *extra, "--link=copy", capsys=capsys)
    assert code == 0, stderr
    pairs = photo_pairs(copies, path)
    size = sum(source.stat().st_size for _, source in pairs)
    assert re.search(rf"3 copies; {size} bytes \([0-9.]+ kB\) copied", stdout), stdout
    for inside, source in pairs:
        assert not inside.is_symlink() and inside.stat().st_ino != source.stat().st_ino
        assert inside.read_bytes() == source.read_bytes()
    read_scene(copies)

    links = tmp_path / "links"
    code, stdout, stderr = run_import("nerfstudio", path, links, *extra, "--link=symlink", capsys=capsys)
    assert code == 0, stderr
    assert "3 symlinks; 0 bytes copied" in stdout and f"--scene={links} --out_dir=runs/ns --allow_outside_paths" in stdout
    for inside, source in photo_pairs(links, path):
        assert inside.is_symlink() and inside.resolve() == source.resolve()
    with pytest.raises(InputError, match=r"views\[0\]\.photo: 'photos/frame_00001\.png' resolves outside"):
        read_scene(links)                             # a symlink out of the folder is refused like ../
    assert len(read_scene(links, allow_outside_paths=True).views) == 3


def test_hard_links_fall_back_to_copies_where_the_file_system_has_none(tmp_path, cams, monkeypatch):
    import errno
    import os

    from jaxdistill import datasets
    from jaxdistill.datasets.common import ImportOptions
    from jaxdistill.scene import place

    path, extra = capture("colmap", tmp_path / "capture", cams)
    scene = datasets.load("colmap", path, ImportOptions(mesh=extra[0].split("=", 1)[1], progress=False,
                                                        work_dir=str(tmp_path / "out")))

    def no_link(src, dst):
        raise OSError(errno.EXDEV, os.strerror(errno.EXDEV))

    monkeypatch.setattr(place.os, "link", no_link)
    placed, placement = place.place_files(scene, tmp_path / "out")
    assert (placement.linked, placement.copied) == (0, 3) and placement.bytes_copied > 0
    assert "3 copies (hard links not possible: Invalid cross-device link)" in placement.summary(tmp_path / "out")
    assert all(v.photo.parent == tmp_path / "out" / "photos" and v.photo.is_file() for v in placed.views)
    with pytest.raises(InputError, match=r"--link: unknown mode 'move'"):
        place.place_files(scene, tmp_path / "out", "move")
