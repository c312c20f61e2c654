"""The vendored conformance suite: loaded whole, its metadata about real cases, each
in-scope case with a probe (a case without one fails the run, never passes it)."""

from __future__ import annotations

from rcan_rtps.conformance import LEVELS, load_suite
from rcan_rtps.conformance.probes import PROBES


def test_the_vendored_suite_loads_every_level() -> None:
    suite = load_suite()
    assert suite.version == "1.4"
    assert [len(suite.upto(level)) for level in LEVELS] == [10, 17, 26]
    assert len({c.id for c in suite.cases}) == len(suite.cases)


def test_the_metadata_names_cases_of_the_suite() -> None:
    suite = load_suite()
    ids = {c.id for c in suite.cases}
    vendored = suite.vendored
    assert set(vendored.out_of_scope) <= ids and set(vendored.adapted) <= ids
    assert not set(vendored.out_of_scope) & set(vendored.adapted)
    assert all(reason.strip() for reason in vendored.out_of_scope.values())


def test_every_in_scope_case_has_a_probe() -> None:
    suite = load_suite()
    unprobed = [c.id for c in suite.cases if c.out_of_scope is None and c.id not in PROBES]
    assert unprobed == []
