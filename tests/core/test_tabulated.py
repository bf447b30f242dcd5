"""Tabulated BSDF files (core.appearance.tabulated): the format's round trip and refusals, and the
interpolation on the sphere (exact at table directions, continuous between)."""
import json
import os

import numpy as np
import pytest

from core.appearance import tabulated
from core.appearance.btf import ubo_directions, unit_vector
from core.appearance.tabulated import TabulatedBSDF, load_tabulated, save_tabulated, sphere_weights


def _sphere(count, seed):
    points = np.random.default_rng(seed).normal(size=(count, 3))
    return points / np.linalg.norm(points, axis=1, keepdims=True)


def _bsdf(light_count=7, view_count=9, seed=0):
    rng = np.random.default_rng(seed)
    light = _sphere(light_count, seed + 1)
    view = _sphere(view_count, seed + 2)
    return TabulatedBSDF(light=light, view=view, values=rng.random((light_count, view_count, 3)),
                         transparency=rng.random((light_count, 3)) * 0.5, period=(0.01, 0.02), units="m",
                         settings={"samples": 64, "seed": seed})


def _save_raw(path, **changes):
    """Write a file as save_tabulated does, then change entries (a damaged or foreign file)."""
    save_tabulated(str(path), _bsdf())
    with np.load(str(path), allow_pickle=False) as archive:
        content = {key: archive[key] for key in archive.files}
    content.update(changes)
    for key in [k for k, v in changes.items() if v is None]:
        del content[key]
    np.savez_compressed(str(path), **content)


def test_round_trip_keeps_everything(tmp_path):
    bsdf = _bsdf()
    path = tmp_path / "cloth.npz"
    assert save_tabulated(str(path), bsdf) == str(path)
    assert [p.name for p in tmp_path.iterdir()] == ["cloth.npz"]  # no temporary left behind
    back = load_tabulated(str(path))
    for key in ("light", "view", "values", "transparency", "period"):
        np.testing.assert_array_equal(getattr(back, key), getattr(bsdf, key))
    assert back.light.dtype == back.values.dtype == np.float32 and back.period.dtype == np.float64
    assert back.units == "m" and back.settings_dict == {"samples": 64, "seed": 0}
    with np.load(str(path), allow_pickle=False) as archive:
        assert archive["format"].item() == "visibake-bsdf" and archive["version"].item() == 1
        assert len(archive["checksum"].item()) == 64


def test_save_replaces_an_existing_file_whole(tmp_path):
    path = tmp_path / "t.npz"
    save_tabulated(str(path), _bsdf(seed=0))
    save_tabulated(str(path), _bsdf(seed=4))
    np.testing.assert_array_equal(load_tabulated(str(path)).values, _bsdf(seed=4).values)


def test_non_finite_and_invalid_tables_are_refused():
    bsdf = _bsdf()
    values = bsdf.values.copy()
    values[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        TabulatedBSDF(bsdf.light, bsdf.view, values, bsdf.transparency, bsdf.period)
    values[0, 0, 0] = -0.5
    with pytest.raises(ValueError, match=">= 0"):
        TabulatedBSDF(bsdf.light, bsdf.view, values, bsdf.transparency, bsdf.period)
    with pytest.raises(ValueError, match="unit"):
        TabulatedBSDF(bsdf.light * 1.1, bsdf.view, bsdf.values, bsdf.transparency, bsdf.period)
    with pytest.raises(ValueError, match="shape"):
        TabulatedBSDF(bsdf.light, bsdf.view, bsdf.values[:, :-1], bsdf.transparency, bsdf.period)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        TabulatedBSDF(bsdf.light, bsdf.view, bsdf.values, bsdf.transparency + 1.0, bsdf.period)
    with pytest.raises(ValueError, match="JSON"):
        TabulatedBSDF(bsdf.light, bsdf.view, bsdf.values, bsdf.transparency, bsdf.period, settings="[1]")
    with pytest.raises(ValueError, match="infinite"):
        TabulatedBSDF(bsdf.light, bsdf.view, bsdf.values, bsdf.transparency, (np.inf, 1.0))


@pytest.mark.parametrize("changes, message", [
    ({"version": np.array(2, np.int64)}, "version 2"),
    ({"format": np.array("merl")}, "not 'visibake-bsdf'"),
    ({"format": None}, "no 'format'"),
    ({"checksum": np.array("0" * 64)}, "checksum"),
    ({"values": np.zeros((7, 9, 3), np.float32)}, "checksum"),
    ({"light": np.tile(np.float32([[0.0, 0.0, 2.0]]), (7, 1))}, "unit"),
    ({"view": np.zeros((9, 2), np.float32)}, "shape"),
    ({"transparency": np.full((7, 3), np.nan, np.float32)}, "NaN"),
    ({"values": np.zeros((7, 9, 3), np.float64)}, "float32"),
    ({"units": None}, "lacks"),
])
def test_loader_refuses_bad_files(tmp_path, changes, message):
    path = tmp_path / "t.npz"
    _save_raw(path, **changes)
    with pytest.raises(ValueError, match=message):
        load_tabulated(str(path))


def test_loader_refuses_what_is_not_an_archive(tmp_path):
    path = tmp_path / "t.npz"
    path.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="npz"):
        load_tabulated(str(path))
    np.save(str(tmp_path / "one.npy"), np.zeros(3))
    with pytest.raises(ValueError, match="single array"):
        load_tabulated(str(tmp_path / "one.npy"))
    save_tabulated(str(path), _bsdf())
    data = bytearray(path.read_bytes())
    data[len(data) // 3:len(data) // 3 + 64] = bytes(64)  # inside the compressed entries
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError):
        load_tabulated(str(path))


def test_checksum_is_reproducible_from_the_documented_recipe(tmp_path):
    bsdf = _bsdf()
    path = tmp_path / "t.npz"
    save_tabulated(str(path), bsdf)
    with np.load(str(path), allow_pickle=False) as archive:
        stored = archive["checksum"].item()
        recomputed = tabulated.checksum(*(archive[k] for k in ("light", "view", "values", "transparency",
                                                                "period")),
                                        archive["units"].item(), archive["settings"].item())
    assert stored == recomputed
    assert json.loads(bsdf.settings) == {"samples": 64, "seed": 0}


def test_evaluation_is_exact_at_table_directions():
    bsdf = _bsdf()
    li, vi = np.meshgrid(np.arange(7), np.arange(9), indexing="ij")
    result = bsdf.evaluate(bsdf.light[li.ravel()], bsdf.view[vi.ravel()])
    assert result.shape == (63, 3) and result.dtype == np.float64
    np.testing.assert_array_equal(result, bsdf.values[li.ravel(), vi.ravel()].astype(np.float64))
    # Directions need not be normalised.
    np.testing.assert_array_equal(bsdf.evaluate(3 * bsdf.light[:1], 0.5 * bsdf.view[2:3]), bsdf.values[0, 2:3])
    np.testing.assert_array_equal(bsdf.evaluate_transparency(bsdf.light), bsdf.transparency.astype(np.float64))


def test_evaluation_stays_within_the_table_and_uses_nine_values():
    bsdf = _bsdf(light_count=30, view_count=30, seed=2)
    light, view = _sphere(500, 10), _sphere(500, 11)
    result = bsdf.evaluate(light, view)
    assert np.all(result >= bsdf.values.min(axis=(0, 1)) - 1e-12)
    assert np.all(result <= bsdf.values.max(axis=(0, 1)) + 1e-12)
    index, weight = sphere_weights(bsdf.light, light)
    assert index.shape == weight.shape == (500, 3)
    np.testing.assert_allclose(weight.sum(axis=1), 1.0)
    assert np.all(weight >= 0)


def test_evaluation_is_continuous_along_a_path():
    # A walk through many neighbour-set changes: plain 3-nearest inverse-distance weighting jumps
    # by ~0.26 on this path; a continuous scheme moves by about slope x step (~3e-3 here, halving
    # with the step).
    thetas, phis = ubo_directions()
    table = unit_vector(thetas, phis)
    rng = np.random.default_rng(5)
    bsdf = TabulatedBSDF(table, table, rng.random((81, 81, 3)), np.zeros((81, 3)), (1.0, 1.0))
    angles = np.linspace(0.0, 2 * np.pi, 40001)
    path = np.stack([0.8 * np.cos(angles), 0.8 * np.sin(angles), np.full_like(angles, 0.6)], axis=1)
    fixed_view = np.tile(table[8], (len(angles), 1))
    along_light = bsdf.evaluate(path, fixed_view)
    along_view = bsdf.evaluate(np.tile(table[3], (len(angles), 1)), path)
    for values in (along_light, along_view):
        steps = np.abs(np.diff(values, axis=0)).max()
        assert steps < 1e-2, steps


def test_weights_are_continuous_where_the_third_and_fourth_neighbours_swap():
    # Four directions on a ring: seen from just off the pole at azimuth 30..60 degrees, the
    # 3rd and 4th nearest (270 and 180 degrees) swap at 45. No weight may move abruptly there.
    table = unit_vector([30, 30, 30, 30], [0, 90, 180, 270])
    queries = unit_vector(np.full(3001, 10.0), np.linspace(30.0, 60.0, 3001))
    index, weight = sphere_weights(table, queries)
    assert set(index[0]) == {0, 1, 3} and set(index[-1]) == {0, 1, 2}
    dense = np.zeros((len(queries), 4))
    np.put_along_axis(dense, index, weight, axis=1)
    assert np.abs(np.diff(dense, axis=0)).max() < 5e-3
    assert dense[1500, 2] == pytest.approx(0.0, abs=1e-12) and dense[1500, 3] == pytest.approx(0.0, abs=1e-12)


def test_small_tables_interpolate_too():
    light = unit_vector([0, 45], [0, 90])
    bsdf = TabulatedBSDF(light, light[:1], np.array([[[1.0, 1, 1]], [[3.0, 3, 3]]]), np.zeros((2, 3)), (1, 1))
    middle = bsdf.evaluate(unit_vector(22.5, 90), light[:1])
    np.testing.assert_allclose(middle, [[2.0, 2.0, 2.0]], atol=1e-12)
    np.testing.assert_array_equal(bsdf.evaluate(light, np.tile(light[:1], (2, 1)))[:, 0], [1.0, 3.0])


def test_queries_are_checked():
    bsdf = _bsdf()
    with pytest.raises(ValueError, match="same shape"):
        bsdf.evaluate(bsdf.light[:2], bsdf.view[:3])
    with pytest.raises(ValueError, match="non-zero"):
        bsdf.evaluate(np.zeros((1, 3)), bsdf.view[:1])
    with pytest.raises(ValueError, match=r"\(K, 3\)"):
        bsdf.evaluate(np.zeros(3), bsdf.view[:1])


def test_no_temporary_file_is_left_when_writing_fails(tmp_path, monkeypatch):
    def failing(*args, **kwargs):
        raise OSError("disk full")
    monkeypatch.setattr(np, "savez_compressed", failing)
    with pytest.raises(OSError):
        save_tabulated(str(tmp_path / "t.npz"), _bsdf())
    assert os.listdir(tmp_path) == []
