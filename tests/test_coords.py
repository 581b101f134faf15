import numpy as np
import pytest

from fedmap.maps.coords import coord_to_pixel, pixel_centres


def test_pixel_centres_convention():
    # 2 rows x 4 cols: x follows columns, y follows rows, centres at (i + 0.5) / n.
    v = pixel_centres(2, 4)
    assert v.shape == (8, 2) and v.dtype == np.float32
    np.testing.assert_allclose(v[0], [0.125, 0.25])  # row 0, col 0
    np.testing.assert_allclose(v[1], [0.375, 0.25])  # row 0, col 1 (row-major)
    np.testing.assert_allclose(v[4], [0.125, 0.75])  # row 1, col 0
    np.testing.assert_allclose(v[7], [0.875, 0.75])  # row 1, col 3


def test_reshape_undoes_flattening():
    h, w = 3, 5
    v = pixel_centres(h, w).reshape(h, w, 2)
    assert np.all(np.diff(v[:, :, 0], axis=1) > 0) and np.all(np.diff(v[:, :, 1], axis=0) > 0)
    np.testing.assert_allclose(v[2, 4], [0.9, 5 / 6], rtol=1e-6)


def test_inverse_round_trip():
    h, w = 7, 11
    rc = coord_to_pixel(pixel_centres(h, w), h, w)
    rows, cols = np.divmod(np.arange(h * w), w)
    np.testing.assert_array_equal(rc, np.stack([rows, cols], 1))


def test_non_positive_size():
    with pytest.raises(ValueError):
        pixel_centres(0, 4)
