"""JSON encoders made once: the compiled encoder that ``json.dumps`` builds anew for every call.

Registrar internal (request keys, record payloads, the check that a value is JSON data). Each
call of ``json.dumps`` or ``JSONEncoder.encode`` makes the compiled encoder of the ``_json``
module with its options before encoding; for values encoded on every request that is a good
part of the cost. :func:`make_encoder` makes it once, with the same options, and returns it.

The encoder keeps no circular-reference markers (they would be shared by threads): a value
that contains itself ends in :class:`RecursionError` instead of ``ValueError("Circular
reference detected")``, and the callers say so. Where the compiled encoder is missing (not
CPython), the returned callable runs ``JSONEncoder.encode``, which raises the ``ValueError``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

__all__ = ["Encoder", "make_encoder"]

#: ``encoder(value, 0)[0]`` is the JSON text of ``value``.
Encoder = Callable[[Any, int], list[str]]


def make_encoder(
    *,
    default: Callable[[Any], Any] | None,
    ensure_ascii: bool,
    separators: tuple[str, str],
    sort_keys: bool,
    allow_nan: bool,
) -> Encoder:
    """The compiled JSON encoder with these options (as ``json.JSONEncoder`` takes them).

    Args:
        default: Called for objects JSON cannot represent (returns something it can, or
            raises TypeError); None: ``JSONEncoder.default`` (raises TypeError).
        ensure_ascii: Escape every non-ASCII character.
        separators: (item separator, key separator).
        sort_keys: Write object keys sorted.
        allow_nan: Write NaN and infinities (else ValueError).

    Returns:
        ``encoder(value, 0)[0]`` is the text; raises as ``JSONEncoder.encode`` does, except
        RecursionError for a value that contains itself.
    """
    encoder = json.JSONEncoder(
        ensure_ascii=ensure_ascii,
        allow_nan=allow_nan,
        sort_keys=sort_keys,
        separators=separators,
        default=default,
    )
    make = getattr(json.encoder, "c_make_encoder", None)  # absent from the typeshed stubs
    if make is None:
        return lambda value, _level: [encoder.encode(value)]
    return make(  # type: ignore[no-any-return]
        None,  # no circular-reference markers
        encoder.default,
        json.encoder.encode_basestring_ascii if ensure_ascii else json.encoder.encode_basestring,
        None,  # no indent
        separators[1],
        separators[0],
        sort_keys,
        False,  # skipkeys
        allow_nan,
    )
