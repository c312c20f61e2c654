"""The sample size bound in force on a domain: ours, or the one the user's CYCLONEDDS_URI
sets after it (inline or in a file), as Cyclone reads it."""

from __future__ import annotations

from pathlib import Path

from cyclonedds.core import DDSException

from rcan_rtps.ros.sample_size import SampleBound, bound_in_force, refused_for_size

_INLINE = "<CycloneDDS><Domain><Internal><MaxSampleSize>{}</MaxSampleSize></Internal></Domain>" \
          "</CycloneDDS>"


def test_ours_is_in_force_unless_the_user_sets_one() -> None:
    assert bound_in_force(1 << 20, "") == SampleBound(1 << 20, "max_sample_bytes")
    assert bound_in_force(1 << 20, "<CycloneDDS/>").source == "max_sample_bytes"
    for text, size in [("64 KiB", 65536), ("2MB", 2 << 20), ("100000B", 100000),
                       ("12345", 12345), (" 1 GiB ", 1 << 30), ("3 kB", 3072)]:
        assert bound_in_force(1 << 20, _INLINE.format(text)).size == size, text


def test_the_last_setting_wins_and_files_are_read(tmp_path: Path) -> None:
    config = tmp_path / "cyclone.xml"
    config.write_text(_INLINE.format("1 MiB").replace("MaxSampleSize", "maxsamplesize"))
    uri = f"{_INLINE.format('64 KiB')},file://{config}"
    assert bound_in_force(256 << 20, uri) == SampleBound(1 << 20,
                                                         "CYCLONEDDS_URI's MaxSampleSize")
    assert bound_in_force(256 << 20, f"{config},{_INLINE.format('5 B')}").size == 5


def test_a_setting_not_read_here_is_an_unknown_bound(tmp_path: Path) -> None:
    assert bound_in_force(1 << 20, _INLINE.format("${SIZE}")).size is None
    assert bound_in_force(1 << 20, str(tmp_path / "absent.xml")).size is None


def test_only_cyclones_error_past_the_bound_is_too_large() -> None:
    error = DDSException(DDSException.DDS_RETCODE_ERROR)
    bound = SampleBound(1024, "max_sample_bytes")
    assert refused_for_size(error, 1025, bound, "a T", 3) is not None
    assert refused_for_size(error, 1022, bound, "a T", 3) is None  # padded to 1024: fits
    assert refused_for_size(error, 1024, bound, "a T", 3) is None
    other = DDSException(DDSException.DDS_RETCODE_PRECONDITION_NOT_MET)
    assert refused_for_size(other, 5000, bound, "a T", 3) is None
    assert refused_for_size(error, 1025, None, "a T", 3) is None  # no domain of ours
