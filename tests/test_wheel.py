"""The wheel a user installs: built from the repository's files alone and installed away from the
checkout, it carries what the main job needs (the embedded bedroom, the shipped model, the run
configs) and its `jaxdistill` command finds them.

The wheel is built without build isolation (so no network is needed; `build` and setuptools >= 77
come with the `test` extra) from a copy of the files git tracks or would track, so a file that
only exists in this working tree cannot make it pass. It is installed with `--no-deps` into a
fresh virtual environment made with `--system-site-packages`, which also sees this interpreter's
site-packages (a path line in a .pth file: jax, absl, ... without reinstalling them; that
folder's own .pth files, such as an editable install's, are not run), and everything is run from
a folder outside the checkout. No distillation runs: `--helpshort` and a config that stops at
flag validation.
"""

from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
import venv
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CONFIGS = sorted(p.name for p in (REPO / "configs").glob("*.cfg"))


def repository_files() -> list[str]:
    """Paths (relative, POSIX) of the files git tracks or would track, that exist in the working tree."""
    out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                         capture_output=True, check=True).stdout.decode()
    return sorted({p for p in out.split("\0") if p and (REPO / p).is_file()})


def files_under(folder: Path) -> dict[str, int]:
    """{relative path: size} of the files under `folder`, caches left out."""
    return {p.relative_to(folder).as_posix(): p.stat().st_size for p in folder.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts}


def run(args, cwd: Path, **kw) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    return subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300, **kw)


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(python, jaxdistill command, a folder outside the checkout) of a venv holding only the wheel."""
    tmp = tmp_path_factory.mktemp("wheel")
    source, dist, env_dir, elsewhere = tmp / "source", tmp / "dist", tmp / "venv", tmp / "elsewhere"
    for name in repository_files():
        if not name.startswith("tests/"):
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, source / name)
    built = run([sys.executable, "-m", "build", "--wheel", "--no-isolation", f"--outdir={dist}", source], cwd=tmp)
    assert built.returncode == 0, built.stdout[-3000:] + built.stderr[-3000:]
    assert "deprecated" not in (built.stdout + built.stderr).lower(), built.stderr[-3000:]
    wheels = list(dist.glob("jaxdistill-*.whl"))
    assert len(wheels) == 1, wheels

    venv.EnvBuilder(system_site_packages=True, with_pip=False).create(env_dir)
    python = env_dir / "bin" / "python"
    purelib = run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=tmp).stdout.strip()
    ours = [p for p in site.getsitepackages() if Path(p).is_dir()]
    (Path(purelib) / "outer_site_packages.pth").write_text("".join(f"{p}\n" for p in ours))
    pip = run([sys.executable, "-m", "pip", f"--python={python}", "install", "--no-deps", "--no-index",
               "--disable-pip-version-check", wheels[0]], cwd=tmp)
    assert pip.returncode == 0, pip.stdout[-3000:] + pip.stderr[-3000:]
    elsewhere.mkdir()
    return python, env_dir / "bin" / "jaxdistill", elsewhere


def test_the_installed_package_holds_the_bedroom_the_model_and_the_configs(installed):
    python, _, elsewhere = installed
    probe = run([python, "-c", """
import json
from pathlib import Path
import jaxdistill, jaxdistill.main as main
from jaxdistill.models import shipped
from jaxdistill.scenes import scene_path
print(json.dumps({"package": jaxdistill.__file__, "bedroom": str(scene_path("bedroom")),
                  "model": str(shipped.shipped_folder()), "configs": main.config_names(),
                  "config_files": {n: str(main.config_path(n)) for n in main.config_names()}}))
"""], cwd=elsewhere)
    assert probe.returncode == 0, probe.stderr[-3000:]
    found = json.loads(probe.stdout.strip().splitlines()[-1])
    package = Path(found["package"]).parent
    assert package.is_relative_to(python.parent.parent), f"jaxdistill was imported from {package}, not the venv"
    assert Path(found["bedroom"]) == package / "scenes" / "bedroom"
    assert files_under(Path(found["bedroom"])) == files_under(REPO / "jaxdistill" / "scenes" / "bedroom")
    assert Path(found["model"]) == package / "models" / "rgbx_rooms"
    assert files_under(Path(found["model"])) == files_under(REPO / "jaxdistill" / "models" / "rgbx_rooms")
    assert found["configs"] == [Path(c).stem for c in CONFIGS] and {"bedroom", "smoke", "thesis"} <= set(found["configs"])
    for name, path in found["config_files"].items():
        assert Path(path).read_bytes() == (REPO / "configs" / f"{name}.cfg").read_bytes(), name
    licences = list(package.parent.glob("jaxdistill-*.dist-info/licenses/LICENSE"))
    assert len(licences) == 1 and licences[0].read_bytes() == (REPO / "LICENSE").read_bytes()


def test_the_installed_command_lists_its_flags_and_reads_a_config_by_name(installed):
    _, command, elsewhere = installed
    short = run([command, "distill", "--helpshort"], cwd=elsewhere)
    assert short.returncode == 1, short.stderr[-3000:]            # absl's help exits 1
    for flag in ("--config", "--scene", "--out_dir", "--steps", "--prior"):
        assert flag in short.stdout
    stopped = run([command, "distill", "--config=bedroom", "--steps=0"], cwd=elsewhere)   # stops at validation
    assert stopped.returncode == 1 and "--steps: must be >= 1" in stopped.stderr, stopped.stderr[-3000:]
    assert "--scene: is required" not in stopped.stderr and "--out_dir: is required" not in stopped.stderr
    unknown = run([command, "distill", "--config=nope"], cwd=elsewhere)
    assert unknown.returncode == 1 and "bedroom, smoke, thesis" in unknown.stderr
    assert not any(elsewhere.iterdir()), "nothing may be written by help or a refused config"
