"""estimators.log_alignment.interp_series against known truth: a linear table is interpolated
exactly between its samples, and a time outside the table, across a gap longer than max_gap_s,
or NaN gets NaN and valid False."""
import numpy as np

from estimators.log_alignment import interp_series


def test_interp_series_is_exact_on_a_line_and_nan_outside_gaps_and_the_table():
    table_t = np.array([5.0, 0.0, 1.0, 2.0, 6.0])                 # out of order: sorted first
    values = np.c_[2.0 * table_t + 1.0, -table_t]
    t = np.array([0.0, 0.5, 1.5, 3.0, 5.5, 6.0, -1.0, 6.5, np.nan])
    out, valid = interp_series(t, table_t, values, max_gap_s=2.0)
    expect_valid = np.array([True, True, True, False, True, True, False, False, False])
    np.testing.assert_array_equal(valid, expect_valid)
    np.testing.assert_allclose(out[valid], np.c_[2.0 * t[valid] + 1.0, -t[valid]], rtol=0, atol=1e-12)
    assert np.isnan(out[~valid]).all()
    one, ok = interp_series([0.25], [0.0, 1.0], [4.0, 8.0])        # (K,) values: one column
    assert one.shape == (1, 1) and ok[0] and one[0, 0] == 5.0
    none, ok = interp_series([0.5], [0.0], [1.0])                   # fewer than two rows
    assert np.isnan(none).all() and not ok.any()
