"""Padded sizes (jaxreg.core._sizes): the size policies and the rows that fill up to them."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxreg.core._sizes import bucket, pad_rows, power_of_two


def test_size_policies():
    assert [bucket(n) for n in (1, 32, 33, 100, 1000)] == [32, 32, 36, 104, 1024]
    assert all(n <= bucket(n) <= 1.125 * n for n in range(33, 5000))
    assert [power_of_two(n) for n in (0, 1, 2, 3, 64, 65)] == [1, 1, 2, 4, 64, 128]
    assert power_of_two(5, 64) == 64 and power_of_two(100, 64) == 128


@pytest.mark.parametrize("kind", [np.asarray, jnp.asarray])
def test_pad_rows_copies_the_last_row_or_fills(kind):
    values = kind(np.arange(6, dtype=np.float32).reshape(3, 2))
    copied = pad_rows(values, 5)
    assert type(copied) is type(values) and copied.dtype == values.dtype
    np.testing.assert_array_equal(copied, [[0, 1], [2, 3], [4, 5], [4, 5], [4, 5]])
    filled = np.asarray(pad_rows(values, 4, np.nan))
    np.testing.assert_array_equal(filled[:3], values)
    assert np.isnan(filled[3]).all()
    assert pad_rows(values, 3) is values
    with pytest.raises(ValueError, match="cannot pad 3 rows to 2"):
        pad_rows(values, 2)
    with pytest.raises(ValueError, match="no last row"):
        pad_rows(values[:0], 2)
    np.testing.assert_array_equal(pad_rows(values[:0], 2, 0.0), np.zeros((2, 2)))
