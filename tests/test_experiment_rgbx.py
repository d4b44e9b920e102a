"""scripts/experiment_rgbx.py reuses a row only when it was made with the current run's settings
and code: each row records both, and a row that differs is refused with its file and the
difference named (run as a CLI on the tiny scene, `trivial` rows only: no model is run)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from tiny_scene import write_tiny_scene

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "experiment_rgbx.py"


def run_script(tmp_path, scene, out):
    env = dict(os.environ, JAXDISTILL_CACHE=str(tmp_path / "cache"))
    return subprocess.run([sys.executable, str(SCRIPT), f"--scenes={scene}", f"--out={out}", "--runs=trivial"],
                          capture_output=True, text=True, env=env, cwd=REPO, timeout=600)


def test_rows_record_settings_and_code_and_only_matching_rows_are_reused(tmp_path):
    scene = tmp_path / "scene"
    write_tiny_scene(scene)
    out = tmp_path / "out"
    first = run_script(tmp_path, scene, out)
    assert first.returncode == 0, first.stderr[-3000:]
    row_file = out / "scene" / "trivial" / "metrics.json"
    row = json.loads(row_file.read_text())
    assert row["settings"] == {"run": "trivial", "scene": str(scene.resolve())}
    assert len(row["code_version"]["source_sha256"]) == 64 and row["ours"]["albedo_psnr"] is not None

    again = run_script(tmp_path, scene, out)                         # same settings, same code: reused
    assert again.returncode == 0, again.stderr[-3000:]
    assert "== scene: trivial" not in again.stdout and json.loads(row_file.read_text()) == row

    stale = dict(row, settings=dict(row["settings"], scene="/elsewhere"),
                 code_version=dict(row["code_version"], source_sha256="0" * 64))
    row_file.write_text(json.dumps(stale))
    refused = run_script(tmp_path, scene, out)
    assert refused.returncode != 0
    assert str(row_file) in refused.stderr and "settings.scene" in refused.stderr and "code version" in refused.stderr

    row_file.write_text(json.dumps({k: v for k, v in row.items() if k not in ("settings", "code_version")}))
    unrecorded = run_script(tmp_path, scene, out)                     # a row written before rows recorded them
    assert unrecorded.returncode != 0 and "records no settings and code version" in unrecorded.stderr

    row_file.unlink()                                                 # deleted: computed again
    assert run_script(tmp_path, scene, out).returncode == 0 and row_file.is_file()
