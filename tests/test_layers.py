"""The layers the networks are built of (`jaxdistill.models.layers`) against Flax's own."""

from __future__ import annotations

from typing import Any

import jax
import numpy as np
import pytest
from flax import errors as flax_errors
from flax import linen as nn

from jaxdistill.models import layers
from tolerance import assert_close


@pytest.mark.parametrize("ours,flax_own,inputs", [
    (layers.Dense(6), nn.Dense(6), np.arange(2 * 5, dtype=np.float32).reshape(2, 5) / 7),
    (layers.Conv(4, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1))),
     nn.Conv(4, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1))),
     np.sin(np.arange(2 * 7 * 6 * 3, dtype=np.float32)).reshape(2, 7, 6, 3)),
    (layers.Embed(9, 5), nn.Embed(9, 5), np.array([[0, 3, 8], [8, 8, 1]], np.int32)),
], ids=["dense", "conv", "embed"])
def test_params_by_shape_are_flax_own_layers_without_tracing_the_initialiser(ours, flax_own, inputs):
    """They init to Flax's own values and apply to its outputs, bit for bit; a stored parameter is
    read without calling its initialiser (Flax's own check traces it on every apply); a parameter
    of the wrong shape is named, and a missing one gets Flax's own error."""
    key = jax.random.key(7)
    params = ours.init(key, inputs)
    reference = flax_own.init(key, inputs)
    assert jax.tree.structure(params) == jax.tree.structure(reference)
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(reference)))
    assert np.array_equal(ours.apply(params, inputs), flax_own.apply(reference, inputs))
    calls = []

    def counting(init):
        return lambda *args: calls.append(args[1]) or init(*args)

    name = "embedding" if isinstance(ours, nn.Embed) else "kernel"
    attribute = f"{name}_init"
    counted_ours = ours.clone(**{attribute: counting(getattr(ours, attribute))})
    counted_flax = flax_own.clone(**{attribute: counting(getattr(flax_own, attribute))})
    counted_ours.apply(params, inputs)
    assert calls == []
    counted_flax.apply(reference, inputs)
    assert len(calls) == 1                                   # Flax's check: one trace of the initialiser
    wrong = jax.tree.map(lambda x: x, params)
    wrong["params"][name] = np.zeros(params["params"][name].shape[:-1] + (1,), np.float32)
    with pytest.raises(flax_errors.ScopeParamShapeError, match=name):
        ours.apply(wrong, inputs)
    missing = []
    for module, tree in ((ours, params), (flax_own, reference)):
        without = {"params": {k: v for k, v in tree["params"].items() if k != name}}
        with pytest.raises(flax_errors.FlaxError, match=name) as error:
            module.apply(without, inputs)
        missing.append(type(error.value))
    assert missing[0] is missing[1], missing                 # Flax's own error for a missing parameter


def test_norm_layers_read_their_parameters_by_shape():
    """GroupNorm and LayerNorm: a stored scale of the wrong shape is named, not broadcast."""
    x = np.linspace(-1, 1, 2 * 3 * 4 * 8, dtype=np.float32).reshape(2, 3, 4, 8)
    for module in (layers.GroupNorm(num_groups=2, epsilon=1e-6), layers.LayerNorm()):
        params = module.init(jax.random.key(0), x)
        assert params["params"]["scale"].shape == (8,)
        wrong = {"params": {**params["params"], "scale": np.ones((1,), np.float32)}}
        with pytest.raises(flax_errors.ScopeParamShapeError, match="scale"):
            module.apply(wrong, x)


def _group_norm_numpy(x, scale, bias, groups, epsilon):
    """GroupNorm as PyTorch defines it, in float64: each sample's group of channels over all positions."""
    x = np.asarray(x, np.float64)
    grouped = x.reshape(x.shape[:-1] + (groups, x.shape[-1] // groups))
    axes = tuple(range(1, grouped.ndim - 2)) + (grouped.ndim - 1,)
    mean = grouped.mean(axis=axes, keepdims=True)
    var = np.square(grouped - mean).mean(axis=axes, keepdims=True)
    return ((grouped - mean) / np.sqrt(var + epsilon)).reshape(x.shape) * scale + bias


@pytest.mark.parametrize("shape,groups", [((2, 5, 6, 8), 2), ((2, 5, 6, 8), 8), ((3, 7, 16), 4), ((1, 3, 4, 5, 6), 3)],
                         ids=["4-per-group", "1-per-group", "tokens", "3-d"])
def test_group_norm_is_the_formula(shape, groups):
    """Per-channel sums then per-group ones give GroupNorm's own formula (float64 NumPy), also for a
    large common offset (a hard case for the variance: 1e3 over unit spread) and a group of one
    channel; bfloat16 activations round only the output."""
    rng = np.random.default_rng(3)
    x = (rng.normal(size=shape) * rng.uniform(0.5, 2, shape[-1]) + 1e3).astype(np.float32)
    scale = rng.uniform(0.5, 1.5, shape[-1]).astype(np.float32)
    bias = rng.normal(size=shape[-1]).astype(np.float32)
    params = {"params": {"scale": scale, "bias": bias}}
    want = _group_norm_numpy(x, scale, bias, groups, 1e-6)
    got = layers.GroupNorm(groups, 1e-6).apply(params, x)
    assert got.dtype == np.float32
    assert_close(got, want, rtol=2e-3, floor=2e-4)      # the float32 input's own rounding at 1e3: 6e-5 per unit
    half = layers.GroupNorm(groups, 1e-6, dtype=jax.numpy.bfloat16).apply(params, x)
    assert half.dtype == jax.numpy.bfloat16
    assert_close(np.asarray(half, np.float32), np.asarray(got), rtol=1e-2, floor=1e-2)


class _ResizeThenConv(nn.Module):
    """The definition: nearest upsampling of the image, then `nn.Conv` 3×3 with padding 1, named "conv"."""

    features: int
    dtype: Any = np.float32

    @nn.compact
    def __call__(self, x, size=None):
        x = layers.nearest_resize(x, size or (2 * x.shape[1], 2 * x.shape[2]))
        return nn.Conv(self.features, (3, 3), padding=((1, 1), (1, 1)), dtype=self.dtype, name="conv")(x)


@pytest.mark.parametrize("shape,features,size", [
    ((2, 5, 7, 6), 4, None), ((2, 5, 7, 6), 4, (10, 14)), ((2, 5, 7, 6), 4, (9, 13)), ((1, 2, 3, 5), 16, None)],
    ids=["x2", "x2-given", "odd", "x2-patches"])
def test_upsample_is_resize_then_conv(shape, features, size):
    """`Upsample2D` (four 2×2 convolutions of the input at ×2; with more output channels than a
    phase has pixels, each a product of patches) against the upsampled image convolved as
    `nn.Conv` does: the same parameters from the same key, the same outputs up to rounding, and
    the same gradients with respect to the input and the kernel."""
    x = np.sin(np.arange(np.prod(shape), dtype=np.float32)).reshape(shape)
    ours, reference = layers.Upsample2D(features), _ResizeThenConv(features)
    params = jax.jit(ours.init, static_argnums=2)(jax.random.key(1), x, size)
    ref_params = jax.jit(reference.init, static_argnums=2)(jax.random.key(1), x, size)
    assert jax.tree.structure(params) == jax.tree.structure(ref_params)
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(ref_params)))
    params = jax.tree.map(lambda p: p + 0.1 * np.cos(np.arange(p.size)).reshape(p.shape).astype(np.float32), params)
    got, want = jax.jit(ours.apply, static_argnums=2)(params, x, size), jax.jit(reference.apply, static_argnums=2)(params, x, size)
    assert got.shape == want.shape == (shape[0],) + (size or (2 * shape[1], 2 * shape[2])) + (features,)
    assert_close(got, want)
    loss = lambda module, p, image: (module.apply(p, image, size) ** 2).sum()  # noqa: E731
    grads = jax.jit(jax.grad(lambda p, image: loss(ours, p, image), argnums=(0, 1)))(params, x)
    ref_grads = jax.jit(jax.grad(lambda p, image: loss(reference, p, image), argnums=(0, 1)))(params, x)
    assert_close(grads[0]["params"]["conv"]["kernel"], ref_grads[0]["params"]["conv"]["kernel"])
    assert_close(grads[1], ref_grads[1])
    half = jax.jit(layers.Upsample2D(features, dtype=jax.numpy.bfloat16).apply, static_argnums=2)(params, x, size)
    assert half.dtype == jax.numpy.bfloat16
    assert_close(np.asarray(half, np.float32), want, rtol=3e-2, floor=3e-2)


@pytest.mark.parametrize("shape,features,path", [
    ((2, 5, 7, 6), 4, "direct"), ((1, 2, 3, 5), 8, "patches"), ((1, 1, 1, 3), 2, "patches"),
    ((1, 4, 6, 8), 8, "winograd"), ((1, 5, 6, 8), 8, "direct")], ids=["lax", "patches", "one-pixel", "winograd", "odd"])
def test_conv3x3_is_flax_conv(shape, features, path, monkeypatch):
    """`Conv3x3` against `nn.Conv` 3×3 with padding 1: the same parameters from the same key; with
    at least as many output pixels as channels it is the same XLA convolution (bit for bit), with
    fewer a product of patches, and with enough channels and pixels (here lowered to 8 and 24) and
    even sides Winograd's (equal up to rounding, gradients too)."""
    monkeypatch.setattr(layers, "WINOGRAD_MIN_CHANNELS", 8)
    monkeypatch.setattr(layers, "WINOGRAD_MIN_PIXELS", 24)
    x = np.cos(np.arange(np.prod(shape), dtype=np.float32)).reshape(shape)
    ours = layers.conv(features, 3, None, np.float32, "default")
    assert isinstance(ours, layers.Conv3x3)
    reference = nn.Conv(features, (3, 3), padding=((1, 1), (1, 1)))
    params, ref_params = jax.jit(ours.init)(jax.random.key(2), x), jax.jit(reference.init)(jax.random.key(2), x)
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(ref_params)))
    params = jax.tree.map(lambda p: p + 0.1 * np.sin(np.arange(p.size)).reshape(p.shape).astype(np.float32), params)
    got, want = jax.jit(ours.apply)(params, x), jax.jit(reference.apply)(params, x)
    if path == "direct":
        np.testing.assert_array_equal(got, want)
    else:
        assert_close(got, want)
    loss = lambda module, p, image: (module.apply(p, image) ** 2).sum()  # noqa: E731
    grads = jax.jit(jax.grad(lambda p, image: loss(ours, p, image), argnums=(0, 1)))(params, x)
    ref_grads = jax.jit(jax.grad(lambda p, image: loss(reference, p, image), argnums=(0, 1)))(params, x)
    for a, b in zip(jax.tree.leaves(grads), jax.tree.leaves(ref_grads)):
        assert_close(a, b)


def test_winograd_is_the_convolution():
    """F(2×2, 3×3) against XLA's 'VALID' convolution of the same padded image: outputs, and the
    gradients with respect to the image and the kernel, equal up to rounding."""
    rng = np.random.default_rng(5)
    image = rng.normal(size=(2, 8, 10, 5)).astype(np.float32)
    taps = rng.normal(size=(3, 3, 5, 7)).astype(np.float32)
    direct = lambda a, k: jax.lax.conv_general_dilated(  # noqa: E731
        a, k, (1, 1), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"), precision="highest")
    got = jax.jit(layers.winograd_3x3, static_argnums=2)(image, taps, "highest")
    assert got.shape == (2, 6, 8, 7)
    assert_close(got, direct(image, taps))
    weights = rng.normal(size=got.shape).astype(np.float32)
    ours = jax.jit(jax.grad(lambda a, k: (layers.winograd_3x3(a, k, "highest") * weights).sum(), argnums=(0, 1)))(image, taps)
    want = jax.jit(jax.grad(lambda a, k: (direct(a, k) * weights).sum(), argnums=(0, 1)))(image, taps)
    for a, b in zip(ours, want):
        assert_close(a, b)


def test_group_norm_refuses_groups_that_do_not_divide_the_channels():
    x = np.ones((4, 3, 3, 10), np.float32)
    with pytest.raises(ValueError, match="10 channels in 4 groups"):
        layers.group_norm(x, np.ones(10, np.float32), np.zeros(10, np.float32), 4, 1e-6)


def test_winograd_in_bfloat16_is_as_close_as_the_direct_convolution():
    """bfloat16 in and out, float32 inside: the error against the float32 convolution of the same
    (bfloat16-rounded) inputs is that of the direct bfloat16 convolution, not the transforms'."""
    rng = np.random.default_rng(9)
    image = jax.numpy.asarray(rng.normal(size=(1, 10, 12, 64)), jax.numpy.bfloat16)
    taps = jax.numpy.asarray(rng.normal(size=(3, 3, 64, 32)) / 24, jax.numpy.bfloat16)
    direct = lambda a, k: jax.lax.conv_general_dilated(  # noqa: E731
        a, k, (1, 1), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    exact = np.asarray(direct(image.astype(np.float32), taps.astype(np.float32)))
    ours = jax.jit(layers.winograd_3x3)(image, taps)
    assert ours.dtype == jax.numpy.bfloat16
    rms = lambda a: float(np.sqrt(np.mean(np.square(np.asarray(a, np.float32) - exact))))  # noqa: E731
    assert rms(ours) <= 1.2 * rms(direct(image, taps))


@pytest.mark.parametrize("shape,features,on_cpu", [
    ((1, 2, 3, 16), 32, "dot"), ((1, 8, 8, 8), 8, "winograd"), ((2, 8, 8, 8), 4, "convolution")],
    ids=["patches", "winograd", "direct"])
def test_only_the_cpu_lowering_takes_another_path(shape, features, on_cpu, monkeypatch):
    """Lowered for CUDA every 3×3 convolution is one XLA convolution, whatever the shape; lowered
    for the CPU the shapes pick the patches' product, Winograd's (here with thresholds lowered
    to 8 channels and 64 pixels) or the convolution."""
    monkeypatch.setattr(layers, "WINOGRAD_MIN_CHANNELS", 8)
    monkeypatch.setattr(layers, "WINOGRAD_MIN_PIXELS", 64)
    image = jax.ShapeDtypeStruct((shape[0], shape[1] + 2, shape[2] + 2, shape[3]), np.float32)
    taps = jax.ShapeDtypeStruct((3, 3, shape[3], features), np.float32)
    traced = jax.jit(layers.convolve_valid).trace(image, taps)
    counts = {}
    for platform in ("cuda", "cpu"):
        text = traced.lower(lowering_platforms=(platform,)).as_text()
        counts[platform] = (text.count("stablehlo.convolution"), text.count("stablehlo.dot_general"))
    assert counts["cuda"] == (1, 0)
    want = {"dot": (0, 1), "winograd": (0, 3), "convolution": (1, 0)}[on_cpu]   # Winograd's: G·g·Gᵀ (2), products
    assert counts["cpu"] == want, counts
