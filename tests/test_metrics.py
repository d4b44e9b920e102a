"""Evaluation metrics against values worked out by hand and a brute-force SSIM."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jaxdistill.evaluate import metrics

C1 = 0.01 ** 2
C2 = 0.03 ** 2


def srgb_decode(v: float) -> float:
    """Linear value whose sRGB encoding is v (v > 0.04045)."""
    return ((v + 0.055) / 1.055) ** 2.4


def brute_force_ssim(x: np.ndarray, y: np.ndarray, mask: np.ndarray, data_range: float = 1.0) -> float:
    """SSIM by explicit loops: 11x11 Gaussian (sigma 1.5) weights over in-image, in-mask pixels."""
    h, w, channels = x.shape
    taps = np.exp(-np.arange(-5, 6) ** 2 / (2 * 1.5 ** 2))
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    values = []
    for c in range(channels):
        for i in range(h):
            for j in range(w):
                if not mask[i, j]:
                    continue
                sw = sx = sy = sxx = syy = sxy = 0.0
                for di in range(-5, 6):
                    for dj in range(-5, 6):
                        r, s = i + di, j + dj
                        if 0 <= r < h and 0 <= s < w and mask[r, s]:
                            wt = taps[di + 5] * taps[dj + 5]
                            a, b = x[r, s, c], y[r, s, c]
                            sw += wt
                            sx += wt * a
                            sy += wt * b
                            sxx += wt * a * a
                            syy += wt * b * b
                            sxy += wt * a * b
                mx, my = sx / sw, sy / sw
                vx, vy, cxy = sxx / sw - mx * mx, syy / sw - my * my, sxy / sw - mx * my
                values.append((2 * mx * my + c1) * (2 * cxy + c2) / ((mx * mx + my * my + c1) * (vx + vy + c2)))
    return float(np.mean(values))


# ----------------------------------------------------------------------------- masks, MSE, PSNR

def test_evaluation_mask_is_hit_and_not_excluded():
    hit = np.array([[True, True, False], [True, False, True]])
    exclude = np.array([[False, True, True], [False, False, False]])
    expected = np.array([[True, False, False], [True, False, True]])
    np.testing.assert_array_equal(metrics.evaluation_mask(hit, exclude), expected)
    np.testing.assert_array_equal(metrics.evaluation_mask(hit), hit)
    with pytest.raises(ValueError, match=r"\(2, 3\)"):
        metrics.evaluation_mask(hit, exclude[:, :2])


def test_psnr_of_constant_error_is_20_db():
    gt = np.zeros((8, 9, 3))
    pred = np.full((8, 9, 3), 0.1)
    assert metrics.mse(pred, gt) == pytest.approx(0.01, rel=1e-14)
    assert metrics.psnr(pred, gt) == pytest.approx(20.0, abs=1e-12)
    assert metrics.psnr(pred, gt, data_range=2.0) == pytest.approx(20.0 + 20 * math.log10(2.0), abs=1e-12)


def test_masked_out_corruption_is_ignored():
    gt = np.zeros((8, 9, 3))
    pred = np.full((8, 9, 3), 0.1)
    pred[:3, :4] = 7.0
    pred[0, 0] = np.nan
    mask = np.ones((8, 9), bool)
    mask[:3, :4] = False
    assert metrics.psnr(pred, gt, mask) == pytest.approx(20.0, abs=1e-12)
    assert metrics.psnr(np.where(np.isnan(pred), 7.0, pred), gt) < 0.0   # unmasked, the corruption dominates


def test_identical_images_give_infinite_psnr_and_zero_mse():
    image = np.random.default_rng(0).uniform(size=(6, 7, 3))
    assert metrics.mse(image, image.copy()) == 0.0
    assert metrics.psnr(image, image.copy()) == math.inf


def test_empty_mask_gives_nan():
    a, b = np.zeros((5, 6, 3)), np.ones((5, 6, 3))
    empty = np.zeros((5, 6), bool)
    for fn in (metrics.mse, metrics.psnr, metrics.ssim, metrics.si_psnr, metrics.si_ssim,
               metrics.angular_error_deg, metrics.grey_mse):
        assert math.isnan(fn(a, b, empty)), fn.__name__


def test_shape_mismatches_raise_naming_the_shapes():
    with pytest.raises(ValueError, match=r"\(4, 4, 3\).*\(4, 5, 3\)"):
        metrics.mse(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))
    with pytest.raises(ValueError, match=r"mask shape \(4, 5\).*\(4, 4\)"):
        metrics.ssim(np.zeros((4, 4, 3)), np.zeros((4, 4, 3)), np.ones((4, 5), bool))
    with pytest.raises(ValueError, match="bool"):
        metrics.psnr(np.zeros((4, 4)), np.zeros((4, 4)), np.ones((4, 4)))


# ----------------------------------------------------------------------------- SSIM

def test_ssim_of_identical_images_is_one():
    image = np.random.default_rng(1).uniform(size=(20, 17, 3))
    assert metrics.ssim(image, image.copy()) == pytest.approx(1.0, abs=1e-12)


def test_ssim_of_two_constants_is_the_luminance_term():
    a, b = 0.3, 0.8
    value = metrics.ssim(np.full((24, 30, 3), a), np.full((24, 30, 3), b))
    assert value == pytest.approx((2 * a * b + C1) / (a * a + b * b + C1), rel=1e-12)
    assert value < 0.9                                               # far from the identical-image value


def test_ssim_checkerboard_against_constant_closed_form():
    # Interior windows of a 0/1 checkerboard: the weight on the centre's parity is E^2 + O^2 with
    # E, O the 1-D Gaussian tap sums at even, odd offsets, so mu = E^2 + O^2 on 1 pixels and 2EO on
    # 0 pixels, var = mu (1 - mu); against a constant c the covariance is 0.
    taps = np.exp(-np.arange(-5, 6) ** 2 / (2 * 1.5 ** 2))
    taps /= taps.sum()
    even, odd = taps[::2].sum(), taps[1::2].sum()
    size, c = 32, 0.4
    board = (np.add.outer(np.arange(size), np.arange(size)) % 2).astype(float)[:, :, None]
    flat = np.full_like(board, c)
    got = metrics.ssim_map(board, flat)[5:-5, 5:-5, 0]
    for value, mu in ((1.0, even ** 2 + odd ** 2), (0.0, 2 * even * odd)):
        expected = (2 * mu * c + C1) * C2 / ((mu * mu + c * c + C1) * (mu * (1 - mu) + C2))
        np.testing.assert_allclose(got[board[5:-5, 5:-5, 0] == value], expected, rtol=1e-10)


def test_ssim_matches_brute_force_with_mask_and_borders():
    rng = np.random.default_rng(2)
    x = rng.uniform(size=(16, 16, 2))
    y = np.clip(x + rng.normal(scale=0.2, size=x.shape), 0, 1)
    mask = np.ones((16, 16), bool)
    mask[4:9, 6:12] = False
    mask[0, :] = False
    got = metrics.ssim(x, y, mask)
    assert got == pytest.approx(brute_force_ssim(x, y, mask), rel=1e-12)
    assert got < 0.95


def test_si_ssim_from_the_scaled_moments_matches_brute_force_on_the_scaled_image():
    """`ssim_and_si_ssim` filters once and scales pred's moments; the reference scales the image
    by the least-squares scales (by hand here) and computes SSIM window by window."""
    rng = np.random.default_rng(5)
    gt = rng.uniform(0.1, 0.9, size=(16, 14, 3))
    pred = np.clip(gt * [0.6, 1.3, 0.9] + rng.normal(scale=0.05, size=gt.shape), 0, None)
    pred[..., 2] = 0.0                                    # an all-zero channel: its scale is 0
    mask = np.ones((16, 14), bool)
    mask[3:8, 2:9] = False
    p, g = pred[mask], gt[mask]
    scales = [(p[:, c] @ g[:, c]) / (p[:, c] @ p[:, c]) if p[:, c].any() else 0.0 for c in range(3)]
    plain, scaled = metrics.ssim_and_si_ssim(pred, gt, mask)
    assert plain == pytest.approx(brute_force_ssim(pred, gt, mask), rel=1e-12)
    assert scaled == pytest.approx(brute_force_ssim(pred * scales, gt, mask), rel=1e-12)
    assert metrics.si_ssim(pred, gt, mask) == scaled and metrics.ssim(pred, gt, mask) == plain
    assert scaled > plain + 0.01                          # the scales matter here
    assert all(np.isnan(metrics.ssim_and_si_ssim(pred, gt, np.zeros((16, 14), bool))))


def test_ssim_ignores_garbage_outside_the_mask_exactly():
    rng = np.random.default_rng(3)
    gt = rng.uniform(size=(20, 20, 3))
    pred = np.clip(gt + rng.normal(scale=0.1, size=gt.shape), 0, 1)
    mask = np.ones((20, 20), bool)
    mask[6:12, 5:15] = False
    dirty_pred, dirty_gt = pred.copy(), gt.copy()
    dirty_pred[6:12, 5:15] = 1e6
    dirty_gt[6:12, 5:15] = np.nan
    clean = metrics.ssim(pred, gt, mask)
    assert metrics.ssim(dirty_pred, dirty_gt, mask) == clean
    assert metrics.ssim(dirty_pred, gt, None) < clean - 0.05          # unmasked, the garbage would count


# ----------------------------------------------------------------------------- scale-invariant

def test_scale_invariant_undoes_per_channel_scales():
    gt = np.random.default_rng(4).uniform(0.2, 0.8, size=(12, 10, 3))
    pred = gt * np.array([0.5, 0.25, 2.0])
    scaled, scales = metrics.scale_invariant(pred, gt)
    np.testing.assert_allclose(scales, [2.0, 4.0, 0.5], rtol=1e-14)
    np.testing.assert_allclose(scaled, gt, rtol=1e-14)
    assert metrics.si_psnr(pred, gt) >= 100.0
    assert metrics.si_ssim(pred, gt) == pytest.approx(1.0, abs=1e-12)
    assert metrics.psnr(pred, gt) < 20.0


def test_scale_invariant_two_pixel_example_by_hand():
    pred = np.array([[1.0, 2.0]])
    gt = np.array([[2.0, 5.0]])
    scaled, scales = metrics.scale_invariant(pred, gt)
    # s = (1*2 + 2*5) / (1 + 4) = 2.4; s*pred = (2.4, 4.8); mse = (0.4^2 + 0.2^2) / 2 = 0.1
    np.testing.assert_allclose(scales, [2.4], rtol=1e-14)
    np.testing.assert_allclose(scaled, [[2.4, 4.8]], rtol=1e-14)
    assert scaled.shape == pred.shape
    assert metrics.si_psnr(pred, gt) == pytest.approx(10.0, abs=1e-12)
    assert metrics.si_psnr(pred, gt, data_range=5.0) == pytest.approx(10 * math.log10(250.0), abs=1e-12)


def test_scale_invariant_zero_channel_and_mask():
    gt = np.ones((2, 2, 2))
    pred = np.zeros((2, 2, 2))
    pred[..., 1] = [[1.0, 3.0], [2.0, 100.0]]
    mask = np.array([[True, True], [True, False]])
    scaled, scales = metrics.scale_invariant(pred, gt, mask)
    # channel 0 all zero -> scale 0; channel 1 on the mask: (1 + 3 + 2) / (1 + 9 + 4) = 6/14
    np.testing.assert_allclose(scales, [0.0, 6.0 / 14.0], rtol=1e-14)
    np.testing.assert_array_equal(scaled[..., 0], 0.0)
    np.testing.assert_allclose(scaled[1, 1, 1], 100.0 * 6.0 / 14.0, rtol=1e-14)   # not clipped


# ----------------------------------------------------------------------------- normals, grey maps

def rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    t = math.radians(degrees)
    return np.eye(3) + math.sin(t) * kx + (1 - math.cos(t)) * kx @ kx


def normals_perpendicular_to(axis: np.ndarray, shape=(6, 7)) -> np.ndarray:
    v = np.random.default_rng(5).normal(size=shape + (3,))
    k = axis / np.linalg.norm(axis)
    v -= (v @ k)[..., None] * k
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_angular_error_of_a_30_degree_rotation():
    axis = np.array([1.0, 2.0, -0.5])
    gt = normals_perpendicular_to(axis)
    pred = gt @ rotation(axis, 30.0).T
    assert metrics.angular_error_deg(pred, gt) == pytest.approx(30.0, abs=1e-10)
    assert metrics.angular_error_deg(5.0 * pred, gt) == pytest.approx(30.0, abs=1e-10)
    assert metrics.angular_error_deg(-gt, gt) == pytest.approx(180.0, abs=1e-10)
    assert metrics.angular_error_deg(gt.copy(), gt) == 0.0


def test_angular_error_zero_vectors_and_mask():
    gt = np.zeros((1, 4, 3))
    gt[..., 2] = 1.0
    pred = gt.copy()
    pred[0, 1] = 0.0                                  # zero vector: 90 degrees
    pred[0, 2] = [0.0, 1.0, 1.0]                      # 45 degrees
    pred[0, 3] = [1.0, 0.0, 0.0]                      # 90 degrees, masked out below
    assert metrics.angular_error_deg(pred, gt) == pytest.approx((0 + 90 + 45 + 90) / 4, abs=1e-12)
    mask = np.array([[True, True, True, False]])
    assert metrics.angular_error_deg(pred, gt, mask) == pytest.approx((0 + 90 + 45) / 3, abs=1e-12)
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        metrics.angular_error_deg(pred[..., :2], gt[..., :2])


def test_grey_mse_uses_channel_zero_only():
    gt = np.full((5, 6), 0.3)
    pred = np.zeros((5, 6, 3))
    pred[..., 0] = 0.4
    pred[..., 1] = 50.0
    assert metrics.grey_mse(pred, gt) == pytest.approx(0.01, rel=1e-12)
    assert metrics.grey_mse(pred, np.repeat(gt[..., None], 4, axis=-1)) == pytest.approx(0.01, rel=1e-12)


# ----------------------------------------------------------------------------- per view, aggregate

def constructed_view():
    """Maps of a 4x5 view with hand-known metrics (see test_evaluate_view_values)."""
    h, w = 4, 5
    ones = np.ones((h, w, 1))
    pred = {
        "albedo": srgb_decode(0.9) * np.ones((h, w, 3)),      # encodes to 0.9
        "roughness": np.concatenate([0.6 * ones, 9.0 * ones, 9.0 * ones], axis=-1),
        "metallic": np.zeros((h, w)),
        "normal": np.broadcast_to([0.0, 1.0, 1.0], (h, w, 3)).copy(),
        "irradiance": np.concatenate([np.ones((h, 2, 1)), 2 * np.ones((h, 3, 1))], axis=1),
    }
    gt = {
        "albedo": np.full((h, w, 3), 1.7),                    # clipped to 1, encodes to 1
        "roughness": np.full((h, w), 0.5),
        "metallic": np.full((h, w, 1), 0.2),
        "normal": np.broadcast_to([0.0, 0.0, 1.0], (h, w, 3)).copy(),
        "irradiance": np.concatenate([2 * np.ones((h, 2, 1)), 5 * np.ones((h, 3, 1))], axis=1),
    }
    return pred, gt


def test_evaluate_view_values():
    pred, gt = constructed_view()
    got = metrics.evaluate_view(pred, gt)
    assert set(got) == {"albedo_psnr", "albedo_ssim", "albedo_si_psnr", "albedo_si_ssim", "roughness_mse",
                        "metallic_mse", "normal_angular_deg", "irradiance_si_psnr", "albedo_shading_leak"}
    assert got["albedo_shading_leak"] == pytest.approx(0.0, abs=1e-12)   # an overall scale is no leak
    assert got["albedo_psnr"] == pytest.approx(20.0, abs=1e-9)                     # sRGB 0.9 vs 1
    assert got["albedo_ssim"] == pytest.approx((2 * 0.9 + C1) / (0.81 + 1 + C1), rel=1e-9)
    assert got["albedo_si_psnr"] >= 100.0
    assert got["albedo_si_ssim"] == pytest.approx(1.0, abs=1e-12)
    assert got["roughness_mse"] == pytest.approx(0.01, rel=1e-12)
    assert got["metallic_mse"] == pytest.approx(0.04, rel=1e-12)
    assert got["normal_angular_deg"] == pytest.approx(45.0, abs=1e-10)
    # irradiance: 2x1 pattern of the hand example, s = 2.4, mse = (8*0.4^2 + 12*0.2^2)/20, range 5
    s = (8 * 2 + 12 * 10) / (8 + 12 * 4)
    error = (8 * (s - 2) ** 2 + 12 * (2 * s - 5) ** 2) / 20
    assert got["irradiance_si_psnr"] == pytest.approx(10 * math.log10(25 / error), abs=1e-10)


@pytest.mark.parametrize("beta", [0.0, 0.35, 1.0, -0.5])
def test_the_shading_leak_is_the_exponent_of_the_light_baked_into_the_albedo(beta):
    """An albedo that is GT albedo × irradiance^β × any scale leaks exactly β (1: the photo itself);
    noise unrelated to the light leaves β in place; masked-out and dark pixels do not count."""
    rng = np.random.default_rng(3)
    h, w = 24, 32
    albedo = rng.uniform(0.05, 0.9, (h, w, 3))
    light = np.exp(rng.normal(0.0, 0.8, (h, w, 1))) * np.array([1.0, 0.9, 0.8])
    grey = np.mean(light, axis=2, keepdims=True)         # the metric regresses luminances
    pred = 3.7 * albedo * grey ** beta
    assert metrics.shading_leak(pred, albedo, light) == pytest.approx(beta, abs=1e-9)
    noisy = pred * np.exp(rng.normal(0.0, 0.05, (h, w, 1)))
    assert metrics.shading_leak(noisy, albedo, light) == pytest.approx(beta, abs=0.03)
    mask = np.zeros((h, w), bool)
    mask[:, :10] = True
    broken = pred.copy()
    broken[:, 10:] = 1e-9                               # outside the mask: ignored
    assert metrics.shading_leak(broken, albedo, light, mask) == pytest.approx(beta, abs=1e-9)
    assert math.isnan(metrics.shading_leak(pred, albedo, np.ones((h, w, 3))))    # uniform light: undefined
    got = metrics.evaluate_view({"albedo": pred}, {"albedo": albedo, "irradiance": light})
    assert got["albedo_shading_leak"] == pytest.approx(beta, abs=1e-9)
    assert "albedo_shading_leak" not in metrics.evaluate_view({"albedo": pred}, {"albedo": albedo})


def test_evaluate_view_skips_maps_missing_on_one_side_and_honours_the_mask():
    pred, gt = constructed_view()
    del pred["normal"], gt["albedo"]
    mask = np.zeros((4, 5), bool)
    mask[:, :2] = True                                 # irradiance: only the 1-vs-2 columns -> exact fit
    got = metrics.evaluate_view(pred, gt, mask)
    assert set(got) == {"roughness_mse", "metallic_mse", "irradiance_si_psnr"}
    assert got["irradiance_si_psnr"] == math.inf
    empty = metrics.evaluate_view(pred, gt, np.zeros((4, 5), bool))
    assert set(empty) == set(got) and all(math.isnan(v) for v in empty.values())


def test_evaluate_view_rejects_unknown_maps_and_bad_shapes():
    pred, gt = constructed_view()
    with pytest.raises(ValueError, match="'specular'"):
        metrics.evaluate_view({**pred, "specular": pred["metallic"]}, gt)
    with pytest.raises(ValueError, match=r"normal: .*\(4, 5, 3\).*\(4, 4, 3\)"):
        metrics.evaluate_view(pred, {**gt, "normal": gt["normal"][:, :4]})


def test_aggregate_means_caps_psnr_and_skips_nan():
    views = [
        {"albedo_psnr": 20.0, "roughness_mse": 0.01, "normal_angular_deg": math.nan},
        {"albedo_psnr": math.inf, "roughness_mse": 0.03, "normal_angular_deg": 10.0},
        {"albedo_psnr": 30.0, "metallic_mse": 0.5, "normal_angular_deg": 20.0},
        {"albedo_psnr": math.nan, "irradiance_si_psnr": math.nan},
    ]
    got = metrics.aggregate(views)
    assert got["albedo_psnr"] == pytest.approx((20 + 100 + 30) / 3, rel=1e-14)
    assert got["roughness_mse"] == pytest.approx(0.02, rel=1e-14)
    assert got["metallic_mse"] == 0.5
    assert got["normal_angular_deg"] == pytest.approx(15.0, rel=1e-14)
    assert math.isnan(got["irradiance_si_psnr"])
    assert got["num_views"] == 4
    assert set(got) == {"albedo_psnr", "roughness_mse", "metallic_mse", "normal_angular_deg",
                        "irradiance_si_psnr", "num_views"}


# ----------------------------------------------------------------------------- seams


def loop_seam_energy(image, region, object_id, mask):
    """Independent reference: walk every pixel, look right and down."""
    image = np.asarray(image, np.float64).reshape(region.shape[0], region.shape[1], -1)
    total, count = 0.0, 0
    h, w = region.shape
    for r in range(h):
        for c in range(w):
            for rr, cc in ((r, c + 1), (r + 1, c)):
                if rr >= h or cc >= w or not (mask[r, c] and mask[rr, cc]):
                    continue
                if object_id[r, c] != object_id[rr, cc] or region[r, c] == region[rr, cc]:
                    continue
                total += float(np.sum((image[r, c] - image[rr, cc]) ** 2))
                count += 1
    return total / count if count else float("nan"), count


def test_seam_energy_of_a_step_on_the_boundary_is_the_step_squared():
    h, w, step = 6, 9, 0.3
    col = np.arange(w)[None, :].repeat(h, 0)
    region = (col >= 4).astype(int)                      # a chart boundary between columns 3 and 4
    smooth = np.stack([0.1 + 0.01 * col, 0.5 + 0.0 * col, 0.2 + 0.02 * col], -1)
    seamy = smooth + step * (col >= 4)[..., None]        # a step exactly on that boundary
    pairs = metrics.seam_pairs(region, np.zeros((h, w), int))
    assert len(pairs[0]) == h                             # one pair per row, across the boundary
    slopes = np.array([0.01, 0.0, 0.02])                 # per channel, across one column
    assert metrics.seam_energy(seamy, pairs) == pytest.approx(np.sum((step + slopes) ** 2), rel=1e-12)
    assert metrics.seam_energy(smooth, pairs) == pytest.approx(np.sum(slopes ** 2), rel=1e-12)
    # the same step off the boundary is not a seam: nothing of it is measured
    off = smooth + step * (col >= 6)[..., None]
    assert metrics.seam_energy(off, pairs) == pytest.approx(np.sum(slopes ** 2), rel=1e-12)
    out = metrics.seam_metrics({"roughness": seamy[..., :1]}, {"roughness": smooth[..., :1]}, pairs)
    assert out["roughness_seam_energy"] == pytest.approx((step + 0.01) ** 2, rel=1e-12)
    ratios = metrics.seam_ratios(metrics.aggregate([out]))
    assert ratios["roughness_seam_ratio"] == pytest.approx(((step + 0.01) / 0.01) ** 2, rel=1e-9)
    assert ratios["roughness_seam_excess"] == pytest.approx((step + 0.01) ** 2 - 0.01 ** 2, rel=1e-9)
    flat = metrics.seam_ratios(metrics.aggregate([metrics.seam_metrics(
        {"metallic": seamy[..., :1]}, {"metallic": np.zeros((h, w, 1))}, pairs)]))
    assert np.isnan(flat["metallic_seam_ratio"]) and flat["metallic_seam_excess"] == pytest.approx((step + 0.01) ** 2)


def test_seam_pairs_and_energy_match_a_loop_reference():
    rng = np.random.default_rng(0)
    region = rng.integers(0, 3, (11, 13))
    object_id = rng.integers(0, 2, (11, 13))
    mask = rng.random((11, 13)) > 0.2
    image = rng.normal(size=(11, 13, 3))
    pairs = metrics.seam_pairs(region, object_id, mask)
    expected, count = loop_seam_energy(image, region, object_id, mask)
    assert len(pairs[0]) == count > 0
    assert metrics.seam_energy(image, pairs) == pytest.approx(expected, rel=1e-12)
    none = metrics.seam_pairs(np.zeros((4, 4), int), np.zeros((4, 4), int))
    assert len(none[0]) == 0 and np.isnan(metrics.seam_energy(np.ones((4, 4)), none))
    with pytest.raises(ValueError, match="one shape"):
        metrics.seam_pairs(region, object_id[:5])


def test_seam_pairs_are_a_loop_references_pairs_in_order_and_their_packed_edges_round_trip():
    """The pairs, in order, of a loop over pixels (right neighbours, then lower ones, each row-major),
    from `seam_edges` and from its two bits a pixel packed and unpacked."""
    rng = np.random.default_rng(3)
    for h, w in ((11, 13), (1, 7), (6, 1), (5, 3)):
        region, object_id, mask = rng.integers(0, 3, (h, w)), rng.integers(0, 2, (h, w)), rng.random((h, w)) > 0.2
        expected = ([], [])
        for dr, dc in ((0, 1), (1, 0)):
            for r in range(h - dr):
                for c in range(w - dc):
                    rr, cc = r + dr, c + dc
                    if (mask[r, c] and mask[rr, cc] and object_id[r, c] == object_id[rr, cc]
                            and region[r, c] != region[rr, cc]):
                        expected[0].append(r * w + c)
                        expected[1].append(rr * w + cc)
        edges = metrics.seam_edges(region, object_id, mask)
        packed = metrics.pack_seam_edges(edges)
        assert packed.dtype == np.uint8 and packed.shape == (metrics.seam_edge_bytes(h, w),) == (-(-2 * h * w // 8),)
        np.testing.assert_array_equal(metrics.unpack_seam_edges(packed, h, w), edges)
        for pairs in (metrics.seam_pairs(region, object_id, mask), metrics.seam_edge_pairs(edges)):
            for got, want in zip(pairs, expected, strict=True):
                assert got.dtype == np.int32
                np.testing.assert_array_equal(got, np.array(want, np.int64))
    with pytest.raises(ValueError, match="are 2 bytes"):
        metrics.unpack_seam_edges(np.zeros(3, np.uint8), 2, 3)
    with pytest.raises(ValueError, match=r"\(2, H, W\)"):
        metrics.seam_edge_pairs(np.zeros((3, 2, 2), bool))


def test_irradiance_seam_energy_is_exposure_free():
    rng = np.random.default_rng(1)
    gt = rng.uniform(0.5, 2.0, (8, 8, 3))
    pred = gt * rng.uniform(0.9, 1.1, (8, 8, 1))
    pairs = metrics.seam_pairs(rng.integers(0, 2, (8, 8)), np.zeros((8, 8), int))
    a = metrics.seam_metrics({"irradiance": pred}, {"irradiance": gt}, pairs)
    b = metrics.seam_metrics({"irradiance": 7.0 * pred}, {"irradiance": 3.0 * gt}, pairs)
    for key in a:
        assert b[key] == pytest.approx(a[key], rel=1e-9)
