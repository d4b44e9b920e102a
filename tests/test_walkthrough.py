"""README's "Your own capture: from photos to Blender", run as written.

The section's command block (the one that sets CAPTURE) runs in bash on tiny COLMAP and nerfstudio
captures (tests/dataset_fixtures.py: 3 views of 32x24 pixels of a box room, the mesh as the
capture's mesh.ply). Only what the README says a reader sets is set: CAPTURE and FORMAT; every
other line runs verbatim, in a working folder of its own (so SCENE and RUN are the README's
relative paths). Visible additions, which the README names: TINY_FLAGS after the distill line and a
free --port after the view line. The prior is the tiny test RGB<->X model through
$JAXDISTILL_RGBX_DIR (the README's commands take weights from there), no --allow_outside_paths.
The COLMAP capture's scene folder is moved to another working folder, and the capture itself
away, between the import and the distillation.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

import dataset_fixtures as fx
from dataset_fixtures import cache, cams  # noqa: F401  (fixtures)

REPO = Path(__file__).resolve().parents[1]
HEADING = "## Your own capture: from photos to Blender"
READER_SETS = ("CAPTURE", "FORMAT")                  # the variables a reader sets; the rest runs as written
TINY_FLAGS = ("--steps=2", "--views_per_step=1", "--render_size=32", "--estimate_steps=4")     # appended to the distill line
ASSIGNMENT = re.compile(r"^([A-Z_]+)=(.*)$")
MAPS = ("albedo", "normal", "roughness", "metallic", "irradiance")


def walkthrough_section() -> str:
    readme = (REPO / "README.md").read_text()
    assert readme.count(HEADING) == 1, f"README.md has no single section {HEADING!r}"
    return readme.split(HEADING, 1)[1].split("\n## ", 1)[0]


def walkthrough_block() -> str:
    """The bash block of the README's walkthrough section that sets CAPTURE."""
    section = walkthrough_section()
    blocks = [b for b in re.findall(r"```bash\n(.*?)```", section, re.S) if b.startswith("CAPTURE=")]
    assert len(blocks) == 1, "the walkthrough section needs one bash block starting with CAPTURE="
    return blocks[0]


def parse_block(block: str) -> tuple[list[tuple[str, str]], list[str]]:
    """(variable assignments in order, commands with their continuation lines joined)."""
    assignments, commands = [], []
    for line in block.replace("\\\n", " ").splitlines():
        if not line.strip():
            continue
        if match := ASSIGNMENT.match(line):
            assert not commands, f"assignment after a command: {line}"
            assignments.append((match[1], match[2]))
        else:
            assert "#" not in line, f"a command line with a comment (flags appended would land in it): {line}"
            commands.append(" ".join(line.split()))
    return assignments, commands


def script(assignments, values: dict[str, str], command: str) -> str:
    """The block's assignments (the reader's ones set to `values`) and one command."""
    lines = [f"{name}={shlex.quote(values[name])}" if name in values else f"{name}={value}"
             for name, value in assignments]
    return "\n".join(["set -eu", *lines, command]) + "\n"


@pytest.fixture(scope="module")
def jax_cache(tmp_path_factory) -> Path:
    """JAX's persistent compilation cache, shared by the module's runs: the second run compiles little."""
    return tmp_path_factory.mktemp("jax_cache")


def environment(rgbx_dir: Path, jax_cache: Path) -> dict[str, str]:
    """This interpreter's `jaxdistill` first on PATH, the tiny RGB<->X model, JAX's compilation cache and the
    test session's JAXDISTILL_CACHE (dataset_fixtures)."""
    return {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
            "JAXDISTILL_RGBX_DIR": str(rgbx_dir), "JAX_PLATFORMS": "cpu",
            "JAX_COMPILATION_CACHE_DIR": str(jax_cache), "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0.5"}


def run(text: str, cwd: Path, env: dict[str, str]) -> str:
    done = subprocess.run(["bash", "-c", text], cwd=cwd, env=env, capture_output=True, text=True, timeout=900)   # a hang guard, not a speed test
    assert done.returncode == 0, f"exit {done.returncode}:\n{text}\n{done.stdout[-3000:]}\n{done.stderr[-5000:]}"
    return done.stdout + done.stderr


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def serve(text: str, cwd: Path, env: dict[str, str], log: Path) -> str:
    """Starts the view command, waits for the URL it prints, fetches the page, then stops it as a reader does
    (Ctrl-C: SIGINT to the process group). The page."""
    import signal

    with log.open("w") as err:
        process = subprocess.Popen(["bash", "-c", text], cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=err,
                                   text=True, start_new_session=True)
        try:
            lines = [process.stdout.readline()]
            while "jaxdistill view: serving" not in lines[-1] and lines[-1] and len(lines) < 30:
                lines.append(process.stdout.readline())    # after viser's banner
            match = re.search(r"at (http://\S+)", lines[-1])
            assert match, (lines, log.read_text()[-3000:])
            with urllib.request.urlopen(match[1], timeout=30) as response:
                assert response.status == 200
                page = response.read().decode(errors="replace")
            os.killpg(process.pid, signal.SIGINT)
            assert process.wait(30) == 0, log.read_text()[-3000:]
        finally:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
    return page


def write_capture(fmt: str, root: Path, cams) -> Path:
    """A capture folder as the README describes it: COLMAP's images/ and sparse/0/ (text), or nerfstudio's
    transforms.json and images/; the mesh as mesh.ply (no UVs: the import unwraps it)."""
    if fmt == "colmap":
        model = fx.write_colmap(root / "sparse" / "0", cams)
        shutil.move(model / "images", root / "images")
    else:
        fx.write_nerfstudio(root, cams)
    fx.write_mesh(root / "mesh.ply", uvs=False)
    return root


def check_run(run_dir: Path, scene: Path) -> None:
    """The outputs the walkthrough names: maps, scene.glb (and scene.usdc with usd-core), metrics.json."""
    import importlib.util

    import trimesh

    for name in MAPS:             # one page: maps/<map>.exr|png (per object: maps/<map>/<object>.exr|png)
        assert (run_dir / "maps" / f"{name}.exr").is_file() and (run_dir / "maps" / f"{name}.png").is_file(), name
    glb = trimesh.load(run_dir / "scene.glb")
    assert len(glb.geometry) == 1 and sum(len(g.faces) for g in glb.geometry.values()) == len(fx.room_mesh().faces)
    assert (run_dir / "scene.usdc").is_file() or importlib.util.find_spec("pxr") is None
    doc = json.loads((run_dir / "metrics.json").read_text())
    assert doc["steps"] == 2 and doc["prior"]["kind"] == "rgbx"
    assert doc["config"]["allow_outside_paths"] is False and Path(doc["config"]["scene"]) == scene


@pytest.mark.parametrize("fmt", ["nerfstudio", "colmap"])
def test_the_readme_walkthrough_runs_as_written_on_a_tiny_capture(fmt, tmp_path, cams, run_rgbx_dir, jax_cache):
    assignments, commands = parse_block(walkthrough_block())
    assert [c.split()[:2] for c in commands] == [["jaxdistill", "import"], ["jaxdistill", "distill"],
                                                 ["jaxdistill", "view"]], commands
    assert {*READER_SETS, "SCENE", "RUN"} <= {name for name, _ in assignments}
    assert "--allow_outside_paths" not in walkthrough_block()
    assert " ".join(TINY_FLAGS) in walkthrough_section()          # the README says what the test appends
    capture = write_capture(fmt, tmp_path / "capture", cams)
    values = dict(zip(READER_SETS, (str(capture), fmt)))
    env = environment(run_rgbx_dir, jax_cache)
    home = tmp_path / "home"
    home.mkdir()
    scene = Path(dict(assignments)["SCENE"])
    assert not scene.is_absolute() and "$" not in str(scene), "SCENE: a folder under the working folder"
    log = run(script(assignments, values, commands[0]), home, env)
    assert "note:" not in log and "0 bytes copied" in log, log
    if fmt == "colmap":           # the scene folder moves whole: to another working folder, the capture away
        moved = tmp_path / "elsewhere"
        (moved / scene).parent.mkdir(parents=True)
        shutil.move(home / scene, moved / scene)
        capture.rename(tmp_path / "capture_gone")
        home = moved
    run(script(assignments, values, f"{commands[1]} {' '.join(TINY_FLAGS)}"), home, env)
    run_dir = home / dict(assignments)["RUN"]
    check_run(run_dir, scene)
    page = serve(script(assignments, values, f"{commands[2]} --port={free_port()}"), home, env, tmp_path / "view.log")
    assert "<html" in page.lower()
