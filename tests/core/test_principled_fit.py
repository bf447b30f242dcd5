"""Fitting Blender's Principled BSDF to a BRDF table (core/appearance/fit.py): recovery of known
parameters from the model's own data, a Lambert table, and bad input. No bpy; the model itself is
checked against Cycles renders by benchmarks/principled_check.py."""
import math

import numpy as np
import pytest

from core.appearance.fit import PrincipledParams, fit_principled, oren_nayar_brdf, principled_brdf


def direction_set(n_theta=4, n_phi=6, max_theta=70.0, phase=0.0):
    out = []
    for t in np.linspace(8.0, max_theta, n_theta):
        for p in np.linspace(0.0, 360.0, n_phi, endpoint=False) + phase:
            t_, p_ = math.radians(t), math.radians(p)
            out.append([math.sin(t_) * math.cos(p_), math.sin(t_) * math.sin(p_), math.cos(t_)])
    return np.array(out)


def pairs():
    lights = direction_set(phase=0.0)
    views = direction_set(phase=15.0)
    return np.repeat(lights, len(views), 0), np.tile(views, (len(lights), 1))


def noisy(values, level=0.01, seed=1):
    """Multiplicative 1% noise: a simulated table is never exact."""
    rng = np.random.default_rng(seed)
    return values * (1.0 + level * rng.standard_normal(values.shape))


# Tolerances: with 1% multiplicative noise on ~580 pairs the parameters are determined to a few
# 0.01 (the log-residual fit is unbiased for symmetric relative noise); roughness and the base colour
# are well constrained (peak width, diffuse level), sheen parameters less so (sheen and diffuse trade
# off at low angles), hence the looser bounds there.

def test_recovers_grey_rough():
    l, v = pairs()
    truth = PrincipledParams(base_color=np.full(3, 0.5), roughness=0.4)
    fit = fit_principled(l, v, noisy(principled_brdf(l, v, truth)))
    assert fit.model == "isotropic", fit.describe()
    np.testing.assert_allclose(fit.base_color, 0.5, atol=0.02)
    assert abs(fit.roughness - 0.4) < 0.03
    assert abs(fit.specular_ior_level - 0.5) < 0.08
    assert fit.anisotropic == 0.0 and fit.sheen_weight == 0.0
    assert fit.rmse < 0.02
    assert "Roughness" in fit.describe() and "RMSE" in fit.describe()


def test_recovers_coloured_sheen():
    l, v = pairs()
    truth = PrincipledParams(base_color=np.array([0.2, 0.3, 0.5]), roughness=0.5, sheen_weight=0.8,
                             sheen_tint=np.array([1.0, 0.5, 0.3]), sheen_roughness=0.4)
    fit = fit_principled(l, v, noisy(principled_brdf(l, v, truth)), try_anisotropy=False)
    assert "sheen" in fit.model, fit.describe()
    np.testing.assert_allclose(fit.base_color, truth.base_color, atol=0.04)
    np.testing.assert_allclose(fit.sheen_weight * fit.sheen_tint, truth.sheen_weight * truth.sheen_tint, atol=0.08)
    assert abs(fit.sheen_roughness - 0.4) < 0.08
    assert abs(fit.roughness - 0.5) < 0.08
    assert fit.rmse < 0.02
    assert fit.candidates["isotropic"] > 0.05  # the sheen is needed


def test_recovers_anisotropy():
    l, v = pairs()
    truth = PrincipledParams(base_color=np.full(3, 0.4), roughness=0.35, anisotropic=0.7, anisotropic_rotation=0.25)
    fit = fit_principled(l, v, noisy(principled_brdf(l, v, truth)), try_sheen=False)
    assert "anisotropic" in fit.model, fit.describe()
    assert abs(fit.anisotropic - 0.7) < 0.08
    # rotation is defined modulo a half turn
    d = (fit.anisotropic_rotation - 0.25 + 0.25) % 0.5 - 0.25
    assert abs(d) < 0.02
    assert abs(fit.roughness - 0.35) < 0.04
    np.testing.assert_allclose(fit.base_color, 0.4, atol=0.03)
    assert fit.rmse < 0.02


def test_lambert_table():
    l, v = pairs()
    rho = np.array([0.6, 0.4, 0.2])
    values = np.broadcast_to(rho / math.pi, l.shape).copy()
    fit = fit_principled(l, v, values, try_sheen=False, try_anisotropy=False)
    # the diffuse lobe sits under the specular layer: base colour is rho divided by
    # (1 - the specular albedo), at most ~10% above rho; the fit may also turn the specular down.
    assert np.all(fit.base_color >= rho - 0.01) and np.all(fit.base_color <= rho / 0.88 + 0.01), fit.describe()
    assert fit.rmse < 0.04, fit.describe()
    assert fit.per_channel_rmse.shape == (3,)


@pytest.mark.parametrize("case, message", [
    ("nan", "NaN"), ("below", "above the horizon"), ("empty", "empty"), ("shape", "(K, 3)"),
    ("negative", "non-negative"), ("unit", "unit vectors")])
def test_bad_input(case, message):
    l, v = pairs()
    f = principled_brdf(l, v, PrincipledParams())
    if case == "nan":
        f[3, 1] = np.nan
    elif case == "below":
        l = l.copy()
        l[0] = [0.6, 0.0, -0.8]
    elif case == "empty":
        l, v, f = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))
    elif case == "shape":
        f = f[:-1]
    elif case == "negative":
        f[0, 0] = -1.0
    elif case == "unit":
        v = v * 2.0
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        fit_principled(l, v, f)


# ------------------------------------------------------------------ Diffuse Roughness (Oren-Nayar)

def test_diffuse_roughness_zero_is_lambert():
    """At Diffuse Roughness 0 (and below Cycles' 1e-5 cutoff) the diffuse lobe is Lambert exactly."""
    l, v = pairs()
    base = np.array([0.7, 0.4, 0.1])
    plain = PrincipledParams(base_color=base, specular_ior_level=0.0)
    np.testing.assert_array_equal(principled_brdf(l, v, plain), np.broadcast_to(base / math.pi, l.shape))
    np.testing.assert_array_equal(oren_nayar_brdf(l, v, base, 0.0), np.broadcast_to(base / math.pi, l.shape))
    for kwargs in ({"specular_ior_level": 0.0}, {}, {"sheen_weight": 0.5, "metallic": 0.3, "anisotropic": 0.5}):
        p = PrincipledParams(base_color=base, roughness=0.3, **kwargs)
        lambert = principled_brdf(l, v, p)
        p.diffuse_roughness = 0.5e-5
        np.testing.assert_array_equal(principled_brdf(l, v, p), lambert)
        # continuous at the cutoff
        p.diffuse_roughness = 2e-5
        np.testing.assert_allclose(principled_brdf(l, v, p), lambert, rtol=1e-4)


def test_oren_nayar_reciprocal_and_back_scattering():
    """The Oren-Nayar term is reciprocal (l <-> v) and scatters back towards the light."""
    l, v = pairs()
    for sigma in (0.3, 1.0):
        p = PrincipledParams(base_color=np.array([0.9, 0.5, 0.2]), specular_ior_level=0.0, diffuse_roughness=sigma)
        f = principled_brdf(l, v, p)
        np.testing.assert_allclose(principled_brdf(v, l, p), f, rtol=1e-12)
        back = principled_brdf(l, l, p)
        forward = principled_brdf(l, l * np.array([-1.0, -1.0, 1.0]), p)
        slanted = l[:, 2] < 0.9
        assert np.all(back[slanted] > forward[slanted])


def _hemisphere(n=200):
    """Cosine-weighted stratified directions: the mean of pi f over them is the albedo."""
    u = (np.arange(n) + 0.5) / n
    u1, u2 = (a.ravel() for a in np.meshgrid(u, u))
    mu, phi = np.sqrt(u1), 2.0 * np.pi * u2
    r = np.sqrt(1.0 - mu * mu)
    return np.stack([r * np.cos(phi), r * np.sin(phi), mu], 1)


@pytest.mark.parametrize("sigma", [0.25, 0.5, 1.0])
def test_oren_nayar_energy(sigma):
    """White Oren-Nayar (no specular): directional albedo <= 1, and = 1 (energy compensation)
    away from grazing views; a white surface with the specular layer stays <= 1 too."""
    lights = _hemisphere()
    for theta in (0.0, 30.0, 60.0, 80.0, 89.0):
        t = math.radians(theta)
        v = np.broadcast_to([math.sin(t), 0.0, math.cos(t)], lights.shape)
        plain = PrincipledParams(base_color=np.ones(3), specular_ior_level=0.0, diffuse_roughness=sigma)
        albedo = math.pi * principled_brdf(lights, v, plain).mean(0)
        # (1e-4: the quadrature's error; E_avg's fit in the model is within 1e-8 of the integral)
        assert np.all(albedo <= 1.0 + 1e-4), (theta, albedo)
        if theta <= 80.0:
            np.testing.assert_allclose(albedo, 1.0, atol=2e-3)
        layered = PrincipledParams(base_color=np.ones(3), roughness=0.4, diffuse_roughness=sigma)
        assert np.all(math.pi * principled_brdf(lights, v, layered).mean(0) <= 1.0 + 5e-3)
    # a coloured surface loses more energy the rougher it is (the multiple bounces are tinted)
    grey = PrincipledParams(base_color=np.full(3, 0.5), specular_ior_level=0.0, diffuse_roughness=sigma)
    v = np.broadcast_to([0.0, 0.0, 1.0], lights.shape)
    assert np.all(math.pi * principled_brdf(lights, v, grey).mean(0) < 0.5)


def test_recovers_diffuse_roughness():
    l, v = pairs()
    truth = PrincipledParams(base_color=np.array([0.3, 0.4, 0.55]), roughness=0.45, diffuse_roughness=0.7)
    fit = fit_principled(l, v, noisy(principled_brdf(l, v, truth)), try_sheen=False, try_anisotropy=False)
    assert fit.model == "isotropic + diffuse roughness", fit.describe()
    assert abs(fit.diffuse_roughness - 0.7) < 0.08, fit.describe()
    np.testing.assert_allclose(fit.base_color, truth.base_color, atol=0.03)
    assert abs(fit.roughness - 0.45) < 0.05
    assert fit.rmse < 0.02
    assert fit.candidates["isotropic"] > 0.03  # Lambert cannot do it
    assert "Diffuse Roughness" in fit.describe()
    np.testing.assert_allclose(fit.evaluate(l, v), principled_brdf(l, v, fit.params()))


def test_diffuse_roughness_off_by_default_for_lambert():
    """A smooth (Lambert) table keeps Diffuse Roughness 0: the rougher model is not 10% better."""
    l, v = pairs()
    truth = PrincipledParams(base_color=np.full(3, 0.5), roughness=0.4)
    fit = fit_principled(l, v, noisy(principled_brdf(l, v, truth)), try_sheen=False, try_anisotropy=False)
    assert fit.diffuse_roughness == 0.0 and fit.model == "isotropic", fit.describe()
    off = fit_principled(l, v, noisy(principled_brdf(l, v, truth)), try_diffuse_roughness=False,
                         try_sheen=False, try_anisotropy=False)
    assert list(off.candidates) == ["isotropic"]
