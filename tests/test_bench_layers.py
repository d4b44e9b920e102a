"""`scripts/bench_layers.py`: each layer's two formulations timed side by side, and their results compared."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_the_quick_cases_time_both_sides_and_agree(tmp_path):
    spec = importlib.util.spec_from_file_location("bench_layers", REPO / "scripts" / "bench_layers.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = tmp_path / "layers.json"
    rows = bench.main(["--quick", "--repeats=1", f"--json={out}"])
    assert [r["kind"] for r in rows] == [c[0] for c in bench.QUICK]
    for row in rows:
        assert row["plain_s"] > 0 and row["ours_s"] > 0
        assert abs(row["ratio"] - row["ours_s"] / row["plain_s"]) < 1e-12
        assert row["max_rel_diff"] < 1e-5, row          # the two formulations compute the same layer
    assert json.loads(out.read_text())["rows"] == rows
    # --cases keeps the cases whose kind or place names one of its words, and refuses a choice of none
    picked = bench.main(["--quick", "--repeats=1", "--cases=group_norm,direct"])
    assert [(r["kind"], r["where"]) for r in picked] == [("conv3x3", "direct"), ("group_norm", "small")]
    try:
        bench.main(["--quick", "--cases=nothing"])
    except SystemExit as stop:
        assert stop.code == 2
    else:
        raise AssertionError("--cases=nothing ran")
