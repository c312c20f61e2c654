"""The sample size bound of a domain: ours, and whether the user's CYCLONEDDS_URI may set
another (inline or in a file); which of Cyclone's errors is a refusal for size."""

from __future__ import annotations

from pathlib import Path

from cyclonedds.core import DDSException

from rcan_rtps.ros.sample_size import (
    UNCHECKED,
    SampleBound,
    bound_in_force,
    past_bound,
    refused_for_size,
)

_INLINE = "<CycloneDDS><Domain><Internal><MaxSampleSize>64 KiB</MaxSampleSize></Internal>" \
          "</Domain></CycloneDDS>"
_OTHER = "<CycloneDDS><Domain><General><AllowMulticast>false</AllowMulticast></General>" \
         "</Domain></CycloneDDS>"


def test_the_user_sets_one_where_the_uri_names_it(tmp_path: Path) -> None:
    assert bound_in_force(1 << 20, "") == SampleBound(1 << 20)
    assert not bound_in_force(1 << 20, _OTHER).user_sets
    assert bound_in_force(1 << 20, f"{_OTHER},{_INLINE}").user_sets
    config = tmp_path / "cyclone.xml"
    config.write_text(_INLINE.replace("MaxSampleSize", "maxsamplesize"))
    assert bound_in_force(1 << 20, f"file://{config}").user_sets
    assert bound_in_force(1 << 20, str(config)).user_sets
    other = tmp_path / "other.xml"
    other.write_text(_OTHER)
    assert not bound_in_force(1 << 20, f"{other}").user_sets
    assert bound_in_force(1 << 20, str(tmp_path / "absent.xml")).user_sets  # (unread: may)
    # (a comma inside inline XML names no file)
    commas = "<CycloneDDS><Domain><General><Interfaces>auto, eth0</Interfaces></General>" \
             "</Domain></CycloneDDS>"
    assert not bound_in_force(1 << 20, commas).user_sets


def test_a_sample_past_our_bound_is_too_large_before_it_is_written() -> None:
    bound = SampleBound(1024)
    assert past_bound(1025, bound, "a T", 3) is not None
    assert past_bound(1022, bound, "a T", 3) is None  # padded to 1024: fits
    assert past_bound(1024, bound, "a T", 3) is None
    assert past_bound(1 << 30, SampleBound(UNCHECKED), "a T", 3) is None
    assert past_bound(5000, SampleBound(1024, user_sets=True), "a T", 3) is None  # (Cyclone's)
    assert past_bound(5000, None, "a T", 3) is None  # no domain of ours


def test_only_cyclones_error_where_the_uri_sets_the_bound_is_too_large() -> None:
    error = DDSException(DDSException.DDS_RETCODE_ERROR)
    said = refused_for_size(error, 100, SampleBound(1024, user_sets=True), "a T", 3)
    assert said is not None and "CYCLONEDDS_URI" in str(said)
    assert refused_for_size(error, 5000, SampleBound(1024), "a T", 3) is None  # (checked before)
    other = DDSException(DDSException.DDS_RETCODE_PRECONDITION_NOT_MET)
    assert refused_for_size(other, 100, SampleBound(1024, user_sets=True), "a T", 3) is None
