"""cyclonedds' get_matched_publications/subscriptions size their buffer by one call and index by
the next: a writer matching in between raised IndexError out of `wait_for_service` (a clean-clone
run of test_concurrent_clients). The listing is asked again instead."""

from __future__ import annotations

from typing import Any, cast

from rcan_rtps.ros.handshake import matched_publications, matched_subscriptions


class _Racing:
    """A reader/writer whose first listings race a new match, as the binding's do."""

    def __init__(self, races: int) -> None:
        self.races = races

    def _listing(self) -> list[int]:
        if self.races:
            self.races -= 1
            raise IndexError("invalid index")
        return [7, 8]

    get_matched_publications = _listing
    get_matched_subscriptions = _listing


def test_a_listing_that_races_a_match_is_asked_again() -> None:
    assert matched_publications(cast(Any, _Racing(2))) == [7, 8]
    assert matched_subscriptions(cast(Any, _Racing(3))) == [7, 8]


def test_a_listing_that_never_settles_is_empty_not_an_error() -> None:
    assert matched_publications(cast(Any, _Racing(100))) == []
