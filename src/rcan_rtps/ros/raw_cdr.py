"""Raw CDR in and out of cyclonedds: the one place that uses the binding's private calls.

cyclonedds-python's `DataWriter.write` serializes a sample with its own (slow) Python codec,
then hands the bytes to `_clayer.ddspy_write`; `DataReader.take` gets bytes from
`_clayer.ddspy_take` and deserializes them the same way. We encode and decode with the
generated codecs (typesys/cdr.py) and pass bytes straight through those two calls, while
topics keep their `IdlStruct` classes, so type names and the XTypes information Cyclone
sends stay exactly as they were.

These calls are not public API. tests/ros/test_raw_cdr.py pins their behaviour on the
versions we ship with; if a binding lacks them, writes and takes go through the public API
(decode to the struct, write it; take structs), slower but the same on the wire.
"""

from __future__ import annotations

from typing import Any

from cyclonedds.core import DDSException
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader

try:
    from cyclonedds._clayer import ddspy_take as _take
    from cyclonedds._clayer import ddspy_write as _write
except ImportError:  # pragma: no cover - a binding without them: the public API
    _take = _write = None

AVAILABLE = _write is not None and _take is not None
RawSample = tuple[bytes, Any]  # CDR (with its 4-byte header), cyclonedds SampleInfo


def write(writer: DataWriter[Any], data: bytes) -> None:
    """Writes one sample given as CDR bytes of the writer's type (XCDR1, with header).

    Like `DataWriter.write` this keeps the GIL inside Cyclone (see readers.py's invariant)."""
    if _write is None or getattr(writer, "_use_version_2", None):
        writer.write(writer.data_type.deserialize(data))  # the public path, same bytes
        return
    pad = -len(data) & 3  # Cyclone takes serialized data in whole 4-byte words, as the binding
    ret = _write(writer._ref, data + bytes(pad) if pad else data)
    if ret < 0:
        raise DDSException(ret, f"occurred while writing a sample in {writer!r}")


def take(reader: DataReader[Any], mask: int, n: int) -> list[RawSample]:
    """Up to `n` samples as (CDR bytes, SampleInfo), invalid ones (disposals) included."""
    if _take is None:  # pragma: no cover
        return [(s.serialize() if s.sample_info.valid_data else b"", s.sample_info)
                for s in reader.take(N=n)]
    found = _take(reader._ref, mask, n)
    if isinstance(found, int):
        raise DDSException(found, f"occurred while taking from {reader!r}")
    return found  # type: ignore[no-any-return]
