"""The layers the networks are built of (`jaxdistill.models.layers`) against Flax's own."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from flax import errors as flax_errors
from flax import linen as nn

from jaxdistill.models import layers


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
