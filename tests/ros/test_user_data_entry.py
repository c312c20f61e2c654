"""USER_DATA entries of our own (`governed_by=…;`) parse back as written, and a value that
would change how the list parses is refused rather than written."""

from __future__ import annotations

import pytest
from cyclonedds.core import Policy
from cyclonedds.qos import Qos

from rcan_rtps.ros.qos import GOVERNED_BY, user_data_entry, user_data_of

RURI = "rcan://registry.local/rcan-rtps/simbot/v1/sim-0001"


def test_an_entry_parses_back_beside_rmws_typehash() -> None:
    text = "typehash=RIHS01_00ff;" + user_data_entry(GOVERNED_BY, RURI)
    parsed = user_data_of(Qos(Policy.Userdata(text.encode())))
    assert parsed == {"typehash": "RIHS01_00ff", GOVERNED_BY: RURI}


def test_no_value_is_no_entry() -> None:
    assert user_data_entry(GOVERNED_BY, "") == ""


@pytest.mark.parametrize("value", ["a;typehash=RIHS01_0", "a=b", "line\nbreak", "\x1b[2J"])
def test_a_value_that_would_split_or_not_print_is_refused(value: str) -> None:
    with pytest.raises(ValueError, match="cannot be a USER_DATA value"):
        user_data_entry(GOVERNED_BY, value)
