"""BTF image folders (core.appearance.btf): the UBO2003 / UTIA sampling and names, the writer's
layout and refusals, the light shift, and round trips through EXR and PNG."""
import json
import os
import struct
import zlib

import numpy as np
import pytest

from core.appearance import btf
from core.errors import OutputRefused

LIGHT = ([0, 15, 30], [0, 60, 30])
VIEW = ([0, 45], [0, 20])


def _images(seed=0, shape=(3, 2, 4, 4, 3)):
    return np.random.default_rng(seed).random(shape).astype(np.float32)


def _write(folder, images=None, image_format="exr", **options):
    images = _images() if images is None else images
    return btf.write_btf_folder(str(folder), images, image_format, (0.5, 0.25), light_angles=LIGHT,
                                view_angles=VIEW, **options)


def test_rings_have_the_ubo2003_counts_and_whole_degree_steps():
    thetas, phis = btf.ubo_directions()
    assert thetas.shape == phis.shape == (81,)
    assert thetas.dtype == phis.dtype == np.int64
    rings, counts = np.unique(thetas, return_counts=True)
    assert rings.tolist() == [0, 15, 30, 45, 60, 75]
    assert counts.tolist() == [1, 6, 12, 18, 20, 24]
    for theta, count in zip(rings, counts):
        ring = phis[thetas == theta]
        assert ring.tolist() == [k * 360 // count for k in range(count)]
        assert ring[0] == 0 and np.all(np.diff(ring) == 360 // count)
    # The database's order is ring by ring, azimuth rising: sorting by (theta, phi) keeps it.
    assert sorted(zip(thetas.tolist(), phis.tolist())) == list(zip(thetas.tolist(), phis.tolist()))


def test_ubo2003_archive_numbers_match_the_order():
    # UBO2003 numbers images 81 * light + view: "00008 tl000 pl000 tv030 pv030", "00162 tl015 pl060 tv000 pv000".
    thetas, phis = btf.ubo_directions()
    assert (thetas[8], phis[8]) == (30, 30)
    assert 162 // 81 == 2 and (thetas[2], phis[2]) == (15, 60)


def test_unit_vectors_are_z_up():
    vectors = btf.unit_vector([0, 90, 90, 45], [0, 0, 90, 180])
    assert vectors.shape == (4, 3)
    np.testing.assert_allclose(vectors[:3], [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-15)
    np.testing.assert_allclose(vectors[3], [-np.sqrt(0.5), 0.0, np.sqrt(0.5)], atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(btf.unit_vector(*btf.ubo_directions()), axis=1), 1.0)
    assert btf.unit_vector(30, 60).shape == (1, 3)


def test_image_names_follow_utia():
    assert btf.image_name(0, 0, 0, 0, "png") == "tv000_pv000/tl000_pl000_tv000_pv000.png"
    assert btf.image_name(15, 300, 75, 345, "exr") == "tv075_pv345/tl015_pl300_tv075_pv345.exr"
    assert btf.image_name(np.int64(30), 30.0, 45, 20, "png") == "tv045_pv020/tl030_pl030_tv045_pv020.png"
    assert btf.parse_image_name("tv075_pv345/tl015_pl300_tv075_pv345.exr") == (15, 300, 75, 345, "exr")
    for bad in [(0, 0, 0, 0, "jpg"), (0, 360, 0, 0, "png"), (7.5, 0, 0, 0, "png"), (-15, 0, 0, 0, "png"),
                (91, 0, 0, 0, "png")]:
        with pytest.raises(ValueError):
            btf.image_name(*bad)
    with pytest.raises(ValueError):
        btf.parse_image_name("tv000_pv000/tl000_pl000_tv015_pv000.png")  # folder and name disagree


def test_light_for_keeps_the_named_direction_by_default():
    np.testing.assert_allclose(btf.light_for(30, 60, 30, 60), btf.unit_vector(30, 60)[0])
    np.testing.assert_allclose(btf.light_for(15, 0, 30, 60), btf.unit_vector(15, 0)[0])


def test_light_for_shifts_only_coinciding_pairs():
    np.testing.assert_allclose(btf.light_for(30, 60, 30, 60, shift_deg=2.0), btf.unit_vector(32, 60)[0])
    np.testing.assert_allclose(btf.light_for(0, 0, 0, 0, shift_deg=2.0), btf.unit_vector(2, 0)[0])
    np.testing.assert_allclose(btf.light_for(15, 0, 30, 60, shift_deg=2.0), btf.unit_vector(15, 0)[0])
    assert btf.light_for(75, 345, 75, 345, shift_deg=7.5).shape == (3,)
    with pytest.raises(ValueError):
        btf.light_for(0, 0, 0, 0, shift_deg=10.0)


def test_writer_lays_out_one_folder_per_view(tmp_path):
    manifest_path = _write(tmp_path)
    files = sorted(str(p.relative_to(tmp_path)).replace(os.sep, "/") for p in tmp_path.rglob("*") if p.is_file())
    expected = sorted(btf.image_name(tl, pl, tv, pv, "exr") for tl, pl in zip(*LIGHT) for tv, pv in zip(*VIEW))
    assert files == sorted(expected + ["btf.json"])
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_dir()) == ["tv000_pv000", "tv045_pv020"]
    manifest = json.loads(open(manifest_path).read())
    assert manifest["format"] == "visibake-btf" and manifest["version"] == 1 and manifest["complete"]
    assert manifest["image_size"] == {"width": 4, "height": 4}
    assert manifest["color_space"] == "linear Rec.709 / sRGB primaries"
    assert manifest["period"] == [0.5, 0.25]
    assert manifest["light_directions"] == [{"theta_deg": t, "phi_deg": p} for t, p in zip(*LIGHT)]
    assert manifest["view_directions"] == [{"theta_deg": t, "phi_deg": p} for t, p in zip(*VIEW)]
    assert manifest["light_shift"]["shift_deg"] == 0.0
    assert sorted(manifest["files"]) == sorted(expected)


def test_exr_round_trip_is_exact(tmp_path):
    images = _images(1)
    images[0, 0, 0, 0] = [5.0, 0.0, 123.5]  # linear HDR values survive
    _write(tmp_path, images)
    directions, back = btf.read_btf_folder(str(tmp_path))
    assert back.shape == (3, 2, 4, 4, 3) and back.dtype == np.float32
    np.testing.assert_array_equal(back, images)
    assert directions.light_thetas.tolist() == LIGHT[0] and directions.view_phis.tolist() == VIEW[1]
    np.testing.assert_allclose(directions.light, btf.unit_vector(*LIGHT))


def test_png_round_trip_holds_the_8bit_srgb_codes(tmp_path):
    images = _images(2)
    _write(tmp_path, images, "png")
    manifest = json.loads((tmp_path / "btf.json").read_text())
    assert manifest["color_space"] == "sRGB" and manifest["pixel_type"] == "uint8"
    _, back = btf.read_btf_folder(str(tmp_path))
    np.testing.assert_array_equal(btf.linear_to_srgb8(back), btf.linear_to_srgb8(images))
    assert np.max(np.abs(back - images)) < 0.01
    # Rows are stored top first: the file's first row is the image's last.
    path = tmp_path / btf.image_name(0, 0, 0, 0, "png")
    data = path.read_bytes()
    assert data[12:16] == b"IHDR" and b"sRGB" in data
    idat_at = data.index(b"IDAT")
    (length,) = struct.unpack(">I", data[idat_at - 4:idat_at])
    raw = zlib.decompress(data[idat_at + 4:idat_at + 4 + length])
    first_row = np.frombuffer(raw[1:1 + 4 * 3], np.uint8).reshape(4, 3)
    np.testing.assert_array_equal(first_row, btf.linear_to_srgb8(images[0, 0, -1]))


def test_png_reader_undoes_every_row_filter(tmp_path):
    rng = np.random.default_rng(3)
    codes = rng.integers(0, 256, (5, 3, 3)).astype(np.uint8)  # top row first, as in the file
    rows, previous = [], np.zeros(9, np.int64)
    for kind, row in zip([0, 1, 2, 3, 4], codes.reshape(5, 9).astype(np.int64)):
        filtered = np.zeros(9, np.int64)
        for x in range(9):
            left = row[x - 3] if x >= 3 else 0
            up, up_left = previous[x], (previous[x - 3] if x >= 3 else 0)
            p = left + up - up_left
            paeth = min((abs(p - left), 0, left), (abs(p - up), 1, up), (abs(p - up_left), 2, up_left))[2]
            predictor = [0, left, up, (left + up) >> 1, paeth][kind]
            filtered[x] = (row[x] - predictor) & 0xFF
        rows.append(bytes([kind]) + bytes(filtered.astype(np.uint8)))
        previous = row

    def chunk(tag, body):
        return struct.pack(">I", len(body)) + tag + body + struct.pack(">I", zlib.crc32(tag + body))
    path = tmp_path / "filters.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 3, 5, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"".join(rows))) + chunk(b"IEND", b""))
    np.testing.assert_array_equal(btf.linear_to_srgb8(btf.read_png(str(path))), codes[::-1])


def test_damaged_png_is_refused(tmp_path):
    _write(tmp_path, image_format="png")
    path = tmp_path / btf.image_name(0, 0, 0, 0, "png")
    data = bytearray(path.read_bytes())
    data[-20] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="damaged"):
        btf.read_png(str(path))


def test_non_finite_pixels_are_refused_before_writing(tmp_path):
    images = _images()
    images[1, 1, 2, 2, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        _write(tmp_path / "a", images)
    assert not (tmp_path / "a").exists()
    writer = btf.BTFWriter(str(tmp_path / "b"), "png", 4, 4, (1, 1), LIGHT, VIEW)
    bad = np.zeros((4, 4, 3), np.float32)
    bad[0, 0, 1] = np.inf
    with pytest.raises(OutputRefused):
        writer.write(0, 0, bad)
    assert not (tmp_path / "b" / "tv000_pv000").exists()
    with pytest.raises(OutputRefused):
        btf.write_png(str(tmp_path / "c.png"), bad)
    assert not (tmp_path / "c.png").exists()


def test_foreign_files_are_refused_unless_overwrite(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(OutputRefused, match="did not write"):
        _write(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]
    _write(tmp_path, overwrite=True)
    assert (tmp_path / "notes.txt").read_text() == "mine"  # overwrite never deletes what is not VisiBake's


def test_a_foreign_image_in_the_layout_is_refused(tmp_path):
    target = tmp_path / "tv000_pv000" / "tl000_pl000_tv000_pv000.exr"
    target.parent.mkdir()
    target.write_bytes(b"someone else's")
    with pytest.raises(OutputRefused):
        _write(tmp_path)
    assert target.read_bytes() == b"someone else's"


def test_a_foreign_manifest_does_not_make_files_visibake_s(tmp_path):
    (tmp_path / "btf.json").write_text(json.dumps({"format": "other", "files": ["x.png"]}))
    (tmp_path / "x.png").write_bytes(b"x")
    with pytest.raises(OutputRefused):
        _write(tmp_path)


def test_rewriting_a_visibake_folder_is_allowed_and_drops_stale_files(tmp_path):
    _write(tmp_path, image_format="png")
    _write(tmp_path, _images(5), image_format="exr")  # files listed in the manifest are VisiBake's
    assert not list(tmp_path.rglob("*.png"))
    manifest = json.loads((tmp_path / "btf.json").read_text())
    assert all(name.endswith(".exr") for name in manifest["files"]) and len(manifest["files"]) == 6
    _, back = btf.read_btf_folder(str(tmp_path))
    np.testing.assert_array_equal(back, _images(5))


def test_an_interrupted_run_leaves_its_files_owned(tmp_path):
    writer = btf.BTFWriter(str(tmp_path), "exr", 4, 4, (1, 1), LIGHT, VIEW)
    writer.write(0, 0, _images()[0, 0])
    with pytest.raises(ValueError, match="missing 5 of 6"):
        writer.finish()
    manifest = json.loads((tmp_path / "btf.json").read_text())
    assert manifest["complete"] is False
    _write(tmp_path)  # the next run may write over them


def test_writing_through_a_link_out_of_the_folder_is_refused(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    folder = tmp_path / "btf"
    writer = btf.BTFWriter(str(folder), "exr", 4, 4, (1, 1), LIGHT, VIEW)
    try:
        os.symlink(outside, folder / "tv045_pv020", target_is_directory=True)
    except (OSError, NotImplementedError):
        pytest.skip("no symbolic links here")
    with pytest.raises(OutputRefused, match="outside"):
        writer.write(0, 1, _images()[0, 1])
    assert not list(outside.iterdir())


def test_writer_refuses_bad_arguments(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputRefused, match="is a file"):
        btf.BTFWriter(str(tmp_path / "file"), "exr", 4, 4, (1, 1), LIGHT, VIEW)
    with pytest.raises(ValueError):
        btf.BTFWriter(str(tmp_path / "a"), "jpg", 4, 4, (1, 1))
    with pytest.raises(ValueError):
        btf.BTFWriter(str(tmp_path / "a"), "exr", 4, 4, (0, 1))
    with pytest.raises(ValueError):
        btf.BTFWriter(str(tmp_path / "a"), "exr", 4, 4, (1, 1), ([0, 0], [0, 90]))  # one direction twice
    with pytest.raises(ValueError):
        btf.BTFWriter(str(tmp_path / "a"), "exr", 4, 4, (1, 1), light_shift_deg=20)
    writer = btf.BTFWriter(str(tmp_path / "b"), "exr", 4, 4, (1, 1), LIGHT, VIEW)
    with pytest.raises(ValueError, match="shape"):
        writer.write(0, 0, np.zeros((4, 5, 3)))


def test_default_writer_uses_the_81_directions(tmp_path):
    writer = btf.BTFWriter(str(tmp_path), "png", 2, 2, (1, 1), light_shift_deg=1.0)
    assert len(writer.planned) == 81 * 81
    assert writer.planned[8] == "tv030_pv030/tl000_pl000_tv030_pv030.png"
    np.testing.assert_allclose(writer.light_direction(8, 8), btf.unit_vector(31, 30)[0])
    np.testing.assert_allclose(writer.view_direction(8), btf.unit_vector(30, 30)[0])


def test_reader_orders_a_folder_without_manifest_as_ubo(tmp_path):
    _write(tmp_path, _images(7))
    os.remove(tmp_path / "btf.json")
    directions, back = btf.read_btf_folder(str(tmp_path))
    assert list(zip(directions.light_thetas, directions.light_phis)) == [(0, 0), (15, 60), (30, 30)]
    np.testing.assert_array_equal(back, _images(7))
    os.remove(tmp_path / btf.image_name(15, 60, 45, 20, "exr"))
    with pytest.raises(ValueError, match="lacks"):
        btf.read_btf_folder(str(tmp_path))


def test_abort_takes_back_a_fresh_run_and_keeps_an_earlier_btf(tmp_path):
    folder = tmp_path / "new" / "btf"
    writer = btf.BTFWriter(str(folder), "png", 4, 4, (1.0, 1.0), light_angles=([0, 15], [0, 0]),
                           view_angles=([0], [0]))
    writer.write(0, 0, np.full((4, 4, 3), 0.5))
    writer.abort()
    assert not folder.exists()  # the images, the manifest and the folder it made
    # Over a complete earlier BTF, an unfinished run leaves a provisional manifest: still VisiBake's.
    first = btf.BTFWriter(str(folder), "png", 4, 4, (1.0, 1.0), light_angles=([0], [0]), view_angles=([0], [0]))
    first.write(0, 0, np.full((4, 4, 3), 0.5))
    first.finish()
    second = btf.BTFWriter(str(folder), "png", 4, 4, (1.0, 1.0), light_angles=([0, 15], [0, 0]),
                           view_angles=([0], [0]))
    second.write(1, 0, np.full((4, 4, 3), 0.25))
    second.abort()
    manifest = json.loads((folder / "btf.json").read_text())
    assert manifest["complete"] is False
    btf.BTFWriter(str(folder), "png", 4, 4, (1.0, 1.0))  # no foreign files: a third run may write
