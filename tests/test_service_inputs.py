"""service/inputs.py's parsing of what a client sends, on values alone (the routes around it: test_service.py)."""

from __future__ import annotations

import pytest
from pydantic_core import PydanticCustomError

from service.inputs import stamp_query


@pytest.mark.parametrize(("text", "stamp"), [("+1718000000000000001", 1718000000000000001), ("+0", 0),
                                             ("0001718000000000000001", 1718000000000000001)])
def test_a_stamp_with_a_plus_sign_or_leading_zeros_is_the_integer_it_writes(text: str, stamp: int) -> None:
    """A sign is part of a decimal integer (``int()`` and JSON writers may put one): ``+N`` is N nanoseconds,
    exactly (not refused as a float of seconds, nor rounded through one)."""
    value = stamp_query(text)
    assert value == stamp and type(value) is int


def test_a_plus_signed_fraction_is_still_refused_as_not_nanoseconds() -> None:
    with pytest.raises(PydanticCustomError, match="expected an integer count of nanoseconds, got 1.5"):
        stamp_query("+1.5")
