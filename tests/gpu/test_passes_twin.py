"""Accumulation of passes and light groups on the GPU against core.transport.passes.accumulate_passes.

Tolerance: the GPU sums and scales in float32, numpy in float64; the inputs are of
order 1-10, so 1e-5 relative (a few float32 ulps after a sum of 5 groups) plus 1e-6
absolute bounds the difference and catches a swapped pass or group (order-1 errors).
"""
import numpy as np
import pytest


@pytest.mark.parametrize("per_group, wants", [(False, {"lighting"}), (True, {"lighting", "direct", "indirect",
                                                                              "irradiance"}),
                                              (True, {"indirect"})])
def test_passes_match_numpy(visibake, gpu_shaders, per_group, wants):
    lighting = visibake.core.transport.groups
    rng = np.random.default_rng(len(wants))
    count = 3001
    albedo = rng.uniform(0, 1, (count, 3))
    groups = {name: lighting.Transported(rng.uniform(0, 10, (count, 3)), rng.uniform(0, 3, (count, 3)))
              for name in ("Sun", "Lamp", "world", "Glow", "Key")}
    ours = gpu_shaders.passes.accumulate_passes(albedo, wants, groups, per_group)
    twin = visibake.core.transport.passes.accumulate_passes(albedo, wants, groups, per_group)
    assert list(ours) == list(twin)
    assert len(ours) == len(wants) * (1 + (5 if per_group else 0))
    for name in twin:
        np.testing.assert_allclose(ours[name], twin[name], rtol=1e-5, atol=1e-6, err_msg=name)
    assert gpu_shaders.passes.accumulate_passes(albedo, wants, {}, per_group) == {}
