"""The console summary printed at the end of a run: ours against the per-view estimates, per
map, the wall time, and where the outputs are."""

from __future__ import annotations

import math
from pathlib import Path

# (metrics.json key, label, unit, higher is better), in the order of the table
ROWS = (
    ("albedo_psnr", "albedo PSNR", "dB", True),
    ("albedo_ssim", "albedo SSIM", "", True),
    ("albedo_seam_ratio", "albedo seam energy / GT's", "", None),
    ("normal_angular_deg", "normal angular error", "deg", False),
    ("normal_seam_ratio", "normal seam energy / GT's", "", None),
    ("roughness_mse", "roughness MSE", "", False),
    ("roughness_seam_ratio", "roughness seam energy / GT's", "", None),
    ("metallic_mse", "metallic MSE", "", False),
    ("metallic_seam_ratio", "metallic seam energy / GT's", "", None),
    ("irradiance_si_psnr", "irradiance scale-inv. PSNR", "dB", True),
    ("irradiance_seam_ratio", "irradiance seam energy / GT's", "", None),
)


def _number(value) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.4g}"


def _better(key: str, higher: bool | None, ours, base) -> str:
    """Which of the two is better: a higher/lower value, or for seam ratios the one nearer 1 (GT's)."""
    if any(v is None or not math.isfinite(v) for v in (ours, base)) or ours == base:
        return ""
    if higher is None:                                     # a ratio to GT: nearer 1 (in log) is better
        if ours <= 0 or base <= 0:
            return ""
        return "ours" if abs(math.log(ours)) < abs(math.log(base)) else "estimates"
    return "ours" if (ours > base) == higher else "estimates"


def summary_table(result: dict, out: Path) -> str:
    """The text table of a finished run's metrics.json `result` (ours vs the per-view estimates per
    map, then wall time and the output paths)."""
    ours, base = result.get("ours") or {}, result.get("baseline_per_view_estimates") or {}
    lines = []
    rows = [(label + (f" ({unit})" if unit else ""), ours.get(key), base.get(key), _better(key, higher, ours.get(key),
                                                                                          base.get(key)))
            for key, label, unit, higher in ROWS if key in ours or key in base]
    if rows:
        width = max(len(r[0]) for r in rows)
        lines.append(f"{'metric':<{width}}  {'ours':>10}  {'estimates':>10}  better")
        lines.append("-" * (width + 32))
        lines += [f"{label:<{width}}  {_number(o):>10}  {_number(b):>10}  {better}" for label, o, b, better in rows]
    else:
        lines.append(result.get("note", "no metrics against ground truth"))
    rerender = result.get("rerender")
    if rerender:
        worst = min(rerender["per_view"], key=rerender["per_view"].get)
        lines.append(f"photos re-rendered from the maps (albedo x irradiance): {rerender['psnr_db']:.2f} dB PSNR, mean "
                     f"of {len(rerender['per_view'])} views (worst {worst}: {rerender['per_view'][worst]:.2f} dB)")
    anchor = result.get("anchor")
    if anchor:
        lines.append(f"overall scale anchored to {anchor['to']}: gains " + "; ".join(
            f"{m} {' '.join(f'{g:.3f}' for g in gains)}" for m, gains in anchor["gains"].items()) + " (--anchor)")
    wall = result.get("wall_seconds")
    if wall is not None:
        lines.append(f"wall time {wall:.1f} s ({result.get('steps_this_run', 0)} steps at "
                     f"{result.get('seconds_per_step', 0.0):.2f} s/step)")
    lines.append(f"outputs in {out}: maps/ (EXR + PNG per map and page), scene.glb (textured mesh, cameras), "
                 + ("scene.usdc (the same in USD), " if (out / "scene.usdc").is_file() else "")
                 + ("renders/, " if (out / "renders").is_dir() else "")
                 + "contact_<map>.png, loss.png, metrics.json")
    return "\n".join(lines)
