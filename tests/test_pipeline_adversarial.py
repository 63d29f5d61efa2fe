"""The HLBVH build pushed to the corners of its configuration space and of its input: settings
that must be refused with a ValueError naming them, and builds whose order, topology and boxes
are checked against independent NumPy references."""

from __future__ import annotations

import pytest

import hlbvh_warp as hb


@pytest.mark.parametrize("bounds", [
    ((0, 0, 0), (10**400, 1, 1)),
    ((-(10**400), 0, 0), (1, 1, 1)),
    # Past Python's 4300-digit limit on printing an integer: the message must still be made.
    ((0, 0, 0), (10**5000, 1, 1)),
    ((0, 0, 0), (10**5000,)),
])
def test_morton_bounds_past_float64_are_refused_with_a_value_error(bounds):
    # NumPy's float64 conversion raised an OverflowError for these, where every other bad
    # setting raises a ValueError naming the field.
    with pytest.raises(ValueError, match="morton_bounds"):
        hb.BuildConfig(morton_bounds=bounds)
