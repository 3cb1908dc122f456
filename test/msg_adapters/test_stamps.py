"""builtin_interfaces/Time <-> int ns: exact, floor convention for negative times."""

from __future__ import annotations

import numpy as np
import pytest
from builtin_interfaces.msg import Time

from msg_adapters.errors import FieldError
from msg_adapters.stamps import header_to_ns, make_header, ns_to_stamp, stamp_to_ns, stamps_to_ns


@pytest.mark.parametrize(
    "ns", [0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789, -1, -1_500_000_000]
)
def test_round_trip_exact(ns):
    stamp = ns_to_stamp(ns)
    assert 0 <= stamp.nanosec < 1_000_000_000
    assert stamp_to_ns(stamp) == ns


def test_negative_uses_floor():
    stamp = ns_to_stamp(-1)
    assert (stamp.sec, stamp.nanosec) == (-1, 999_999_999)


def test_no_float_rounding_at_large_epochs():
    ns = 2_000_000_000_000_000_001  # float64 cannot hold this exactly
    assert stamp_to_ns(ns_to_stamp(ns)) == ns


def test_out_of_range():
    with pytest.raises(FieldError, match=str(2**31 * 10**9)):
        ns_to_stamp(2**31 * 10**9)


def test_vectorised_and_header():
    secs, nsecs = np.array([1, 2, -1]), np.array([5, 999_999_999, 0])
    np.testing.assert_array_equal(
        stamps_to_ns(secs, nsecs), [1_000_000_005, 2_999_999_999, -1_000_000_000]
    )
    with pytest.raises(FieldError, match="1000000000"):
        stamps_to_ns([0], [1_000_000_000])
    header = make_header(3_000_000_007, "f")
    assert header.frame_id == "f" and header_to_ns(header) == 3_000_000_007
    assert stamp_to_ns(Time(sec=3, nanosec=7)) == 3_000_000_007
