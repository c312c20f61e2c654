"""Issue 24 item 5: the verifier of signed RCAN 3.x COMMANDs (rcan._signatures).

The official SDK is the oracle: `rcan.signing.sign_message` (ML-DSA-65, FIPS 204, through
dilithium-py) signs `_canonical_message_bytes`; the bridge makes those bytes again from the JSON
body it received and verifies with `cryptography`. Ed25519 over the same bytes is our extension.
"""

from __future__ import annotations

import base64
import json
from typing import Any

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from hypothesis import given, settings
from hypothesis import strategies as st
from rcan.message import RCANMessage
from rcan.signing import MLDSAKeyPair, _canonical_message_bytes, sign_message

from rcan_rtps.rcan import decode_object
from rcan_rtps.rcan._signatures import (
    KeyLoadError,
    load_inline_key,
    load_public_key,
    signature_value,
    signed_bytes,
    verifies,
)

pytestmark = pytest.mark.offline

TARGET = "rcan://registry.local/clearpath/husky/v1/a200-0001"
SDK_KEY = MLDSAKeyPair.generate()
ED_KEY = Ed25519PrivateKey.generate()


def received(msg: RCANMessage) -> dict[str, Any]:
    """The body as the bridge decodes it after a client sent `to_dict()` as JSON."""
    return decode_object(json.dumps(msg.to_dict()).encode())


def sdk_signed(params: dict[str, Any]) -> RCANMessage:
    msg = RCANMessage(cmd="move", target=TARGET, params=params, confidence=0.7)
    signed: RCANMessage = sign_message(msg, SDK_KEY)
    return signed


# One signed message for the flips (the same length in every example).
SIGNED = sdk_signed({"linear_x": 0.4})
ED_MESSAGE = _canonical_message_bytes(sdk_signed({"angular_z": 0.1}))
ED_SIGNATURE = ED_KEY.sign(ED_MESSAGE)


def raw_signature(msg: RCANMessage) -> bytes:
    value = signature_value(msg.signature["value"])  # type: ignore[index]
    assert value is not None
    return value


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**53), 2**53)
    | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner,
                                                                max_size=3),
    max_leaves=8)


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(st.text(max_size=10), json_values, max_size=4),
       st.floats(min_value=0, max_value=4e9, allow_nan=False))
def test_the_signed_bytes_are_the_sdks(params: dict[str, Any], timestamp: float) -> None:
    msg = RCANMessage(cmd="move", target=TARGET, params=params, timestamp=timestamp)
    assert signed_bytes(received(msg)) == _canonical_message_bytes(msg)


def test_an_sdk_signature_verifies() -> None:
    msg = sdk_signed({"linear_x": 0.4, "label": "Grüße ☃"})
    key = load_public_key("ml-dsa-65", SDK_KEY.public_key)
    assert verifies(key, signed_bytes(received(msg)), raw_signature(msg))


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_any_flipped_byte_of_message_or_signature_is_refused(data: st.DataObject) -> None:
    message, signature = signed_bytes(received(SIGNED)), raw_signature(SIGNED)
    key = load_public_key("ml-dsa-65", SDK_KEY.public_key)
    flip_message = data.draw(st.booleans(), label="flip the message (else the signature)")
    target = bytearray(message if flip_message else signature)
    at = data.draw(st.integers(0, len(target) - 1), label="byte")
    target[at] ^= data.draw(st.integers(1, 255), label="mask")
    if flip_message:
        assert not verifies(key, bytes(target), signature)
    else:
        assert not verifies(key, message, bytes(target))


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_ed25519_over_the_same_bytes_and_any_flip_refused(data: st.DataObject) -> None:
    message, signature = ED_MESSAGE, ED_SIGNATURE
    key = load_inline_key("ed25519", base64.b64encode(
        ED_KEY.public_key().public_bytes_raw()).decode())
    assert verifies(key, message, signature)
    which = data.draw(st.sampled_from(["message", "signature"]))
    target = bytearray(message if which == "message" else signature)
    target[data.draw(st.integers(0, len(target) - 1))] ^= data.draw(st.integers(1, 255))
    if which == "message":
        assert not verifies(key, bytes(target), signature)
    else:
        assert not verifies(key, message, bytes(target))


def test_a_signature_value_has_one_spelling() -> None:
    raw = ED_KEY.sign(b"x")  # 64 bytes: the last base64 character has 4 unused bits
    text = base64.urlsafe_b64encode(raw).decode()
    assert signature_value(text) == raw
    assert signature_value(text.rstrip("=")) == raw  # unpadded, as JWS writes it
    last = text.rstrip("=")[-1]
    sloppy = text.rstrip("=")[:-1] + chr(ord(last) + 1)  # same bytes, an unused bit set
    assert base64.urlsafe_b64decode(sloppy + "==") == raw
    assert signature_value(sloppy) is None
    assert signature_value(base64.b64encode(b"\xfb\xff" * 10).decode()) is None  # + and /
    assert signature_value(text + "=") is None
    assert signature_value(text[:-3] + "=") is None
    assert signature_value("a") is None


def test_keys_load_raw_pem_or_inline_and_never_as_another_algorithm(tmp_path: Any) -> None:
    ed_public = ED_KEY.public_key()
    pem = ed_public.public_bytes(serialization.Encoding.PEM,
                                 serialization.PublicFormat.SubjectPublicKeyInfo)
    assert load_public_key("ed25519", pem) == ed_public
    assert load_public_key("ed25519", ed_public.public_bytes_raw()) == ed_public
    with pytest.raises(KeyLoadError, match="not an ml-dsa-65"):
        load_public_key("ml-dsa-65", pem)
    ml_public = load_public_key("ml-dsa-65", SDK_KEY.public_key)
    ml_pem = ml_public.public_bytes(serialization.Encoding.PEM,
                                    serialization.PublicFormat.SubjectPublicKeyInfo)
    assert load_public_key("ml-dsa-65", ml_pem) == ml_public
    with pytest.raises(KeyLoadError):
        load_public_key("ml-dsa-65", SDK_KEY.public_key[:-1])
    with pytest.raises(KeyLoadError, match="1952"):
        load_inline_key("ml-dsa-65", base64.b64encode(b"\0" * 32).decode())
    with pytest.raises(KeyLoadError, match="base64"):
        load_inline_key("ed25519", "not base64!")
