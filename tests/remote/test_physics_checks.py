"""The physics services' vector check in C agrees with their item-by-item check."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from evclock.remote._checks import all_finite_numbers, is_finite_number

ITEMS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(min_value=-1e301, max_value=1e301),
    st.integers(),
    st.integers(min_value=-(10**400), max_value=10**400),
    st.booleans(),
    st.sampled_from([1e300, -1e300, math.nextafter(1e300, 0), 2**1000, None, "1.0"]),
    st.lists(st.floats(), max_size=2),
)


@given(st.lists(ITEMS, max_size=12))
def test_the_vector_check_accepts_exactly_what_the_item_check_accepts(items: list[object]) -> None:
    assert all_finite_numbers(items) == all(is_finite_number(item) for item in items)


def test_the_vector_check_refuses_each_kind_of_bad_item() -> None:
    good = [0.0, 1, -2.5]
    for bad in (math.nan, math.inf, -math.inf, True, 1e300, 10**400, "1", None, [1.0]):
        assert not all_finite_numbers([*good, bad]), bad
        assert not all_finite_numbers([bad, *good]), bad
    assert all_finite_numbers(good)
    assert all_finite_numbers([])
