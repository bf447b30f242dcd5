"""MERL isotropic BRDF tables (core.appearance.merl): the file's layout and its checks, the
half/difference angles, the lookup, and filling a table from scattered samples."""
import os

import numpy as np
import pytest

from core.appearance import merl

SHAPE = (3, 90, 90, 180)


def _hemisphere(count, turn=0.0):
    """(count, 3) nearly uniform directions above the horizon (a Fibonacci spiral, z > 0)."""
    i = np.arange(count) + 0.5
    z = 1.0 - i / count
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i + turn
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _pairs(count=100):
    """Every pair of two different hemisphere sets: (count**2, 3) light and view."""
    lights, views = _hemisphere(count), _hemisphere(count, turn=1.0)
    return np.repeat(lights, count, axis=0), np.tile(views, (count, 1))


def _random_hemisphere(rng, count):
    """(count, 3) directions uniform in solid angle above the horizon."""
    z = rng.uniform(0.0, 1.0, count)
    phi = rng.uniform(0.0, 2.0 * np.pi, count)
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _stored_table(seed):
    """A table of numbers a MERL file can hold (stored number times the channel scale) with
    some no-data cells."""
    rng = np.random.default_rng(seed)
    stored = rng.uniform(0.0, 3000.0, SHAPE)
    table = stored * merl.CHANNEL_SCALES[:, None, None, None]
    table[:, ~merl.valid_cells()] = merl.NO_DATA
    return table


# --- the file ---------------------------------------------------------------------------------


def test_write_read_round_trip_is_bit_exact(tmp_path):
    table = _stored_table(1)
    path = tmp_path / "tile.binary"
    merl.write_merl(path, table)
    assert os.path.getsize(path) == 12 + 3 * 1458000 * 8
    back = merl.read_merl(path)
    assert back.dtype == np.float64 and back.shape == SHAPE
    assert np.array_equal(back, table)
    assert os.listdir(tmp_path) == ["tile.binary"]  # the temporary file was renamed, not left


def test_file_layout_matches_the_reference_reader(tmp_path):
    # One cell per channel, found where the reference reader looks: header, then channel c's
    # block, cell phi_d + theta_d * 180 + theta_h * 180 * 90, each stored / scale.
    table = np.zeros(SHAPE)
    i, j, k = 7, 40, 123
    table[:, i, j, k] = [0.5, 0.25, 2.0]
    table[0, 89, 89, 179] = merl.NO_DATA
    path = tmp_path / "one.binary"
    merl.write_merl(path, table)
    raw = path.read_bytes()
    assert np.array_equal(np.frombuffer(raw[:12], "<i4"), [90, 90, 180])
    stored = np.frombuffer(raw, "<f8", offset=12)
    cell = k + j * 180 + i * 180 * 90
    for c in range(3):
        assert stored[c * 1458000 + cell] * merl.CHANNEL_SCALES[c] == table[c, i, j, k]
    assert stored[1458000 - 1] == -1.0
    assert np.count_nonzero(stored) == 4


def test_any_values_round_trip_to_an_ulp(tmp_path):
    table = np.random.default_rng(2).lognormal(0.0, 2.0, SHAPE)
    path = tmp_path / "any.binary"
    merl.write_merl(path, table)
    assert np.max(np.abs(merl.read_merl(path) - table) / table) <= 2.5e-16


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, -0.5])
def test_write_refuses_bad_values_and_writes_nothing(tmp_path, bad):
    table = np.ones(SHAPE)
    table[2, 3, 4, 5] = bad
    path = tmp_path / "bad.binary"
    with pytest.raises(ValueError, match="not written"):
        merl.write_merl(path, table)
    assert os.listdir(tmp_path) == []


def test_write_refuses_a_wrong_shape(tmp_path):
    with pytest.raises(ValueError, match="shape"):
        merl.write_merl(tmp_path / "x.binary", np.ones((3, 90, 90, 360)))


def test_read_rejects_a_bad_header(tmp_path):
    good = tmp_path / "good.binary"
    merl.write_merl(good, np.zeros(SHAPE))
    data = good.read_bytes()
    for dims in ([90, 90, 90], [180, 90, 90]):
        path = tmp_path / "bad.binary"
        path.write_bytes(np.array(dims, "<i4").tobytes() + data[12:])
        with pytest.raises(ValueError, match=r"not a MERL BRDF file: header dimensions"):
            merl.read_merl(path)
    path.write_bytes(b"MERL")
    with pytest.raises(ValueError, match="header"):
        merl.read_merl(path)


def test_read_rejects_a_truncated_or_padded_file(tmp_path):
    path = tmp_path / "t.binary"
    merl.write_merl(path, np.zeros(SHAPE))
    data = path.read_bytes()
    path.write_bytes(data[:-8])
    with pytest.raises(ValueError, match="truncated"):
        merl.read_merl(path)
    path.write_bytes(data + b"\0")
    with pytest.raises(ValueError, match="bytes after its data"):
        merl.read_merl(path)


def test_read_maps_any_negative_stored_number_to_no_data(tmp_path):
    path = tmp_path / "n.binary"
    stored = np.ones(SHAPE)
    stored[1, 2, 3, 4] = -7.0
    path.write_bytes(merl.HEADER.tobytes() + stored.astype("<f8").tobytes())
    table = merl.read_merl(path)
    assert table[1, 2, 3, 4] == merl.NO_DATA
    assert table[0, 0, 0, 0] == merl.CHANNEL_SCALES[0]


# --- angles -----------------------------------------------------------------------------------


def test_half_difference_of_simple_pairs():
    a = 0.3
    # Mirror pair: h is the normal, the light's own angles are (theta_d, phi_d).
    th, ph, td, pd = merl.half_difference([[np.sin(a), 0.0, np.cos(a)]], [[-np.sin(a), 0.0, np.cos(a)]])
    np.testing.assert_allclose([th[0], ph[0], td[0], pd[0]], [0.0, 0.0, a, 0.0], atol=1e-15)
    # Light at the normal, view at 2a in the x-z plane: h at a, the light rotated by -a
    # about y points to -x.
    th, ph, td, pd = merl.half_difference([[0.0, 0.0, 1.0]], [[np.sin(2 * a), 0.0, np.cos(2 * a)]])
    np.testing.assert_allclose([th[0], ph[0], td[0], abs(pd[0])], [a, 0.0, a, np.pi], atol=1e-15)


def test_direction_pair_inverts_half_difference():
    rng = np.random.default_rng(3)
    n = 5000
    th = rng.uniform(1e-3, np.pi / 2, n)
    td = rng.uniform(1e-3, np.pi / 2 - 1e-3, n)
    pd = rng.uniform(-np.pi, np.pi, n)
    ph = rng.uniform(-np.pi, np.pi, n)
    light, view = merl.direction_pair(th, td, pd, ph)
    np.testing.assert_allclose(np.linalg.norm(light, axis=1), 1.0, atol=1e-14)
    got = merl.half_difference(light, view)
    for want, have in zip((th, ph, td, pd), got):
        wrapped = np.angle(np.exp(1j * (have - want)))
        assert np.max(np.abs(wrapped)) < 1e-11
    # And the other way: any pair above the horizon comes back from its angles.
    light, view = _random_hemisphere(rng, n), _random_hemisphere(rng, n)
    th, ph, td, pd = merl.half_difference(light, view)
    light2, view2 = merl.direction_pair(th, td, pd, ph)
    assert np.max(np.abs(light2 - light)) < 1e-12 and np.max(np.abs(view2 - view)) < 1e-12


def test_swapping_light_and_view_gives_the_same_cell():
    rng = np.random.default_rng(4)
    light, view = _random_hemisphere(rng, 20000), _random_hemisphere(rng, 20000)
    th, _, td, pd = merl.half_difference(light, view)
    th2, _, td2, pd2 = merl.half_difference(view, light)
    np.testing.assert_allclose(np.angle(np.exp(1j * (pd2 - pd))) ** 2, np.pi ** 2, rtol=1e-9)
    assert np.array_equal(merl.cell_index(th, td, pd), merl.cell_index(th2, td2, pd2))


def test_cell_index_and_centres():
    th, td, pd = merl.cell_centres()
    assert th.shape == td.shape == pd.shape == (1458000,)
    assert np.array_equal(merl.cell_index(th, td, pd), np.arange(1458000))
    assert th[0] == (0.5 / 90) ** 2 * np.pi / 2
    # The reference's clamps and folds: theta_h <= 0 and angles past the range, phi_d < 0.
    assert merl.cell_index(-0.1, 0.0, 0.0) == 0
    assert merl.cell_index(np.pi, np.pi, np.pi) == 1458000 - 1
    assert merl.cell_index(0.0, 0.0, -np.pi / 2) == 90
    # theta_h's index is the square root one: 10.5 cells' theta_h is in cell 10.
    assert merl.cell_index((10.5 / 90) ** 2 * np.pi / 2, 0.0, 0.0) == 10 * 180 * 90
    with pytest.raises(ValueError, match="finite"):
        merl.cell_index(np.nan, 0.0, 0.0)


def test_valid_cells_are_those_whose_centre_pair_is_above_the_horizon():
    light, view = merl.direction_pair(*merl.cell_centres())
    above = (light[:, 2] > 0) & (view[:, 2] > 0)
    assert np.array_equal(merl.valid_cells().ravel(), above)


# --- lookup -----------------------------------------------------------------------------------


def test_evaluate_looks_up_the_cell_and_zeroes_below_the_horizon():
    rng = np.random.default_rng(5)
    table = rng.uniform(0.1, 2.0, SHAPE)
    table[:, ~merl.valid_cells()] = merl.NO_DATA
    cells = rng.integers(0, 1458000, 3000)
    th, td, pd = (a[cells] for a in merl.cell_centres())
    light, view = merl.direction_pair(th, td, pd, rng.uniform(-np.pi, np.pi, cells.size))
    got = merl.evaluate(table, light, view)
    want = table.reshape(3, -1)[:, cells].T
    above = (light[:, 2] > 0) & (view[:, 2] > 0)
    assert np.array_equal(got[above], want[above])
    assert np.all(got[~above] == 0.0) and np.any(~above)
    with pytest.raises(ValueError, match="NaN"):
        merl.evaluate(table, np.full((1, 3), np.nan), np.ones((1, 3)))


# --- filling from samples ---------------------------------------------------------------------


def test_lambert_fills_to_rho_over_pi_in_every_valid_cell():
    light, view = _pairs()
    rho = np.array([0.2, 0.5, 0.8])
    table = merl.fill_from_samples(light, view, np.tile(rho / np.pi, (len(light), 1)))
    valid = merl.valid_cells()
    assert np.all(table[:, ~valid] == merl.NO_DATA)
    relative = table[:, valid] / (rho / np.pi)[:, None] - 1.0
    assert np.max(np.abs(relative)) < 0.005


DIFFUSE = np.array([0.3, 0.4, 0.5])
SPECULAR = np.array([0.1, 0.2, 0.3])


def _glossy(light, view, exponent=50):
    """Lambert plus normalised Blinn-Phong in cos(theta_h): (K, 3) 1/sr."""
    h = light + view
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    lobe = (exponent + 2) / (2 * np.pi) * np.clip(h[:, 2], 0.0, 1.0) ** exponent
    return DIFFUSE / np.pi + SPECULAR * lobe[:, None]


def test_glossy_fill_evaluates_close_to_the_brdf():
    light, view = _pairs()
    table = merl.fill_from_samples(light, view, _glossy(light, view))
    rng = np.random.default_rng(1)
    ql, qv = _random_hemisphere(rng, 2000), _random_hemisphere(rng, 2000)
    truth = _glossy(ql, qv)
    th, _, td, pd = merl.half_difference(ql, qv)
    has_data = merl.valid_cells().ravel()[merl.cell_index(th, td, pd)]
    # A pair close to the horizon can fall in a cell whose centre is below it (no data,
    # evaluated as 0, as MERL's own tables do): a thin band, 13 of these 2000 pairs.
    assert np.count_nonzero(~has_data) < 30
    relative = (merl.evaluate(table, ql, qv) - truth)[has_data] / truth[has_data]
    rmse = np.sqrt(np.mean(relative ** 2))
    # Measured 0.020 (0.064 with the old fill: phi_d width fixed in cells, min_weight 6). Of
    # it, 0.012 is the table's own nearest-cell lookup (a table of the exact values at the
    # cell centres scores that); the rest is the 100 x 100 sample set, which has no sample with
    # theta_h < 1.1 degrees (theta_h index < 10) and ~40 in the next ten theta_h rows, so the
    # lobe's top is extrapolated (merl_direction_sets puts pairs there). 0.03 leaves room for
    # BLAS rounding, not for a worse method.
    assert rmse < 0.03


def test_anisotropic_samples_fill_their_average_over_phi_h():
    # A BRDF of the pair's (theta_h, theta_d, phi_d) times 1 + 0.5 cos(2 phi_h): the isotropic
    # table is its mean over phi_h, the factor dropped.
    light, view = _pairs()
    _, phi_h, _, _ = merl.half_difference(light, view)
    base = np.array([0.1, 0.2, 0.3])
    table = merl.fill_from_samples(light, view, base * (1.0 + 0.5 * np.cos(2.0 * phi_h))[:, None])
    valid = merl.valid_cells()
    relative = table[:, valid] / base[:, None] - 1.0
    # Measured: mean -0.004, RMS 0.038 (a kernel's few samples do not cover phi_h evenly;
    # 0.028 with the kernel of fixed phi_d width, which grew wider to gather its samples).
    assert abs(np.mean(relative)) < 0.01
    assert np.sqrt(np.mean(relative ** 2)) < 0.05


def test_fill_refuses_bad_samples():
    light, view = _pairs(10)
    values = np.ones((100, 3))
    with pytest.raises(ValueError, match="NaN"):
        merl.fill_from_samples(light, view, np.where(np.arange(100)[:, None] == 3, np.nan, values))
    with pytest.raises(ValueError, match="NaN"):
        merl.fill_from_samples(np.where(np.arange(100)[:, None] == 3, np.nan, light), view, values)
    with pytest.raises(ValueError, match="horizon"):
        merl.fill_from_samples(light * [1, 1, -1], view, values)
    with pytest.raises(ValueError, match="negative"):
        merl.fill_from_samples(light, view, -values)
    with pytest.raises(ValueError, match="shape"):
        merl.fill_from_samples(light, view, values[:, :2])


def test_fill_from_one_sample_gives_every_valid_cell_its_value():
    table = merl.fill_from_samples([[0.0, 0.0, 1.0]], [[0.6, 0.0, 0.8]], [[0.1, 0.2, 0.3]])
    valid = merl.valid_cells()
    assert np.max(np.abs(table[:, valid] / np.array([0.1, 0.2, 0.3])[:, None] - 1.0)) < 1e-6


# --- choosing the directions ------------------------------------------------------------------


@pytest.mark.parametrize("lights, views", [(1, 1), (1, 7), (7, 1), (3, 2), (50, 20), (20, 50), (100, 100)])
def test_direction_sets_are_unit_above_the_horizon_and_sized(lights, views):
    light, view = merl.merl_direction_sets(lights, views)
    assert light.shape == (lights, 3) and view.shape == (views, 3)
    assert light.dtype == np.float64 and view.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(light, axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(view, axis=1), 1.0, atol=1e-14)
    assert np.all(light[:, 2] > 0.0)
    assert np.all(view[:, 2] >= merl.VIEW_MIN_Z)
    assert np.all(np.isfinite(light)) and np.all(np.isfinite(view))


def test_direction_sets_are_deterministic_for_a_seed():
    a = merl.merl_direction_sets(40, 60, seed=3)
    b = merl.merl_direction_sets(40, 60, seed=3)
    c = merl.merl_direction_sets(40, 60, seed=4)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[1], c[1])


def _partner_rows(anchors, partners):
    """For each anchor, the theta_h index-space row u of its nearest-to-mirror partner: (A,)."""
    mirrors = anchors * [-1.0, -1.0, 1.0]
    nearest = np.argmax(mirrors @ partners.T, axis=1)
    theta_h, _, _, _ = merl.half_difference(anchors, partners[nearest])
    return np.sqrt(theta_h / (np.pi / 2)) * 90.0


@pytest.mark.parametrize("lights, views", [(100, 100), (30, 90), (90, 30)])
def test_every_direction_of_the_smaller_set_has_a_partner_near_its_mirror(lights, views):
    light, view = merl.merl_direction_sets(lights, views)
    anchors, partners = (light, view) if views >= lights else (view, light)
    rows = _partner_rows(anchors, partners)
    # Spread over the first PARTNER_THETA_H_ROWS theta_h rows (a partner of a light near the
    # horizon is tilted up past that to keep the view above VIEW_MIN_Z: a few).
    assert np.count_nonzero(rows < merl.PARTNER_THETA_H_ROWS) >= 0.9 * len(anchors)
    assert np.count_nonzero(rows < 10.0) >= 0.2 * len(anchors)


def test_fibonacci_sets_have_no_pair_in_the_first_theta_h_rows():
    # What the partners are for: 100 x 100 Fibonacci directions (turned apart, or the same
    # set twice as the BRDF job had them) put no pair below theta_h row 10 (1.1 degrees).
    for views in (_hemisphere(100, turn=1.0), _hemisphere(100)):
        light, view = np.repeat(_hemisphere(100), 100, axis=0), np.tile(views, (100, 1))
        theta_h, _, _, _ = merl.half_difference(light, view)
        assert np.min(np.sqrt(theta_h / (np.pi / 2)) * 90.0) > 10.0
    light, view = merl.merl_direction_sets(100, 100)
    light, view = np.repeat(light, 100, axis=0), np.tile(view, (100, 1))
    theta_h, _, _, _ = merl.half_difference(light, view)
    assert np.count_nonzero(np.sqrt(theta_h / (np.pi / 2)) * 90.0 < 10.0) >= 30


def test_direction_sets_fill_the_peak_better_than_fibonacci_sets():
    rng = np.random.default_rng(8)
    # Pairs uniform in the table's index space over the peak rows (theta_h index < 20).
    theta_h = (rng.uniform(0.0, 20.0, 6000) / 90.0) ** 2 * np.pi / 2
    theta_d = rng.uniform(0.0, np.pi / 2, 6000)
    phi_d = rng.uniform(0.0, np.pi, 6000)
    ql, qv = merl.direction_pair(theta_h, theta_d, phi_d, rng.uniform(-np.pi, np.pi, 6000))
    keep = merl.valid_cells().ravel()[merl.cell_index(theta_h, theta_d, phi_d)] & (ql[:, 2] > 0) & (qv[:, 2] > 0)
    ql, qv = ql[keep], qv[keep]
    truth = _glossy(ql, qv)

    def peak_rmse(lights, views):
        pl, pv = np.repeat(lights, len(views), axis=0), np.tile(views, (len(lights), 1))
        table = merl.fill_from_samples(pl, pv, _glossy(pl, pv))
        return np.sqrt(np.mean(((merl.evaluate(table, ql, qv) - truth) / truth) ** 2))

    chosen = peak_rmse(*merl.merl_direction_sets(100, 100))
    fibonacci = peak_rmse(_hemisphere(100), _hemisphere(100))
    # Measured 0.024 against 0.153, both with today's fill: a factor of 6; asserting 3.
    assert chosen < fibonacci / 3.0
    assert chosen < 0.05


def test_direction_sets_refuse_no_directions():
    with pytest.raises(ValueError, match="at least one"):
        merl.merl_direction_sets(0, 10)
    with pytest.raises(ValueError, match="at least one"):
        merl.merl_direction_sets(10, 0)


def test_lambert_stays_exact_with_the_direction_sets():
    light, view = merl.merl_direction_sets(60, 80)
    pl, pv = np.repeat(light, len(view), axis=0), np.tile(view, (len(light), 1))
    rho = np.array([0.2, 0.5, 0.8])
    table = merl.fill_from_samples(pl, pv, np.tile(rho / np.pi, (len(pl), 1)))
    valid = merl.valid_cells()
    assert np.max(np.abs(table[:, valid] / (rho / np.pi)[:, None] - 1.0)) < 0.005
