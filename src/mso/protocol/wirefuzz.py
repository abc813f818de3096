"""Random wire messages for fuzzing: every message type, fields of the right type but of random
meaning (apps, vertices, nodes and edges that may or may not exist, absurd numbers), built from
the message union's own type information so a new message type is fuzzed without being listed.

Driven by a :class:`random.Random`, so the Hypothesis tests (``st.randoms()``) and the
million-frame benchmark (``bench/fuzz.py``) share it.
"""

from __future__ import annotations

import random
import typing
from typing import Any

import msgspec
import msgspec.inspect as mi

from mso.protocol import messages as m

MESSAGE_TYPES: tuple[type[Any], ...] = typing.get_args(m.Message)
NAMES = ("pipe", "src", "sink", "mid", "N1", "N2", "N3", "N9", "", "client", "x" * 300)
INTS = (0, 1, 2, -1, 3, 7, 2**31, 2**62, 2**63 - 1, -(2**63))
FLOATS = (0.0, 1.0, -1.0, 1e308, -1e308, float("inf"), float("nan"), 1e-300)


def value(rng: random.Random, t: mi.Type, depth: int = 0) -> Any:
    """A random value of wire type ``t`` (as msgspec encodes it)."""
    if isinstance(t, mi.IntType):
        return rng.choice(INTS) if rng.random() < 0.5 else rng.randint(-5, 100)
    if isinstance(t, mi.FloatType):
        return rng.choice(FLOATS) if rng.random() < 0.5 else rng.uniform(-10, 1e4)
    if isinstance(t, mi.StrType):
        return rng.choice(NAMES)
    if isinstance(t, mi.BoolType):
        return rng.random() < 0.5
    if isinstance(t, mi.BytesType):
        return rng.randbytes(rng.choice((0, 1, 8, 64)))
    if isinstance(t, mi.NoneType):
        return None
    if isinstance(t, mi.UnionType):
        return value(rng, rng.choice(t.types), depth)
    if isinstance(t, mi.ListType):
        n = 0 if depth > 2 else rng.choice((0, 1, 2, 5))
        return [value(rng, t.item_type, depth + 1) for _ in range(n)]
    if isinstance(t, mi.DictType):
        n = 0 if depth > 2 else rng.choice((0, 1, 3))
        return {
            value(rng, t.key_type, depth + 1): value(rng, t.value_type, depth + 1) for _ in range(n)
        }
    if isinstance(t, mi.RawType):
        return msgspec.Raw(msgspec.msgpack.encode(rng.choice(NAMES)))
    # AnyType and what else: a small random structure
    pick = rng.randrange(6 if depth < 2 else 4)
    if pick == 0:
        return rng.choice(INTS)
    if pick == 1:
        return rng.choice(NAMES)
    if pick == 2:
        return rng.choice(FLOATS)
    if pick == 3:
        return None
    if pick == 4:
        return [value(rng, mi.AnyType(), depth + 1) for _ in range(rng.randrange(4))]
    return {rng.choice(NAMES): value(rng, mi.AnyType(), depth + 1) for _ in range(2)}


_INFO: dict[type[Any], mi.StructType] = {}


def _info(cls: type[Any]) -> mi.StructType:
    info = _INFO.get(cls)
    if info is None:
        found = mi.type_info(cls)
        assert isinstance(found, mi.StructType)
        info = _INFO[cls] = found
    return info


def message(rng: random.Random, types: tuple[type[Any], ...] = MESSAGE_TYPES) -> m.Message:
    """A message of a random type whose fields are well-typed but mean anything."""
    while True:
        info = _info(rng.choice(types))
        fields = [value(rng, f.type) for f in info.fields]
        try:  # through the decoder, as a frame would come: what it refuses is not a message
            return m.decode(msgspec.msgpack.encode([info.tag, *fields]))
        except (msgspec.DecodeError, msgspec.ValidationError):
            continue


def payload(rng: random.Random, src: str, dst: str) -> bytes:
    """A frame payload: mostly a well-formed envelope around a random message, sometimes a
    truncated, bit-flipped or random one."""
    body = m.wrap(src, dst, message(rng))
    roll = rng.random()
    if roll < 0.8:
        return body
    if roll < 0.87:
        return body[: rng.randrange(len(body))]
    if roll < 0.94:
        flipped = bytearray(body)
        flipped[rng.randrange(len(flipped))] ^= 1 << rng.randrange(8)
        return bytes(flipped)
    return rng.randbytes(rng.randrange(64))
