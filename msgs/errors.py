"""Errors of the wire codec. All are ``WireError`` (a ``ValueError``), so a receiver can catch one
class, count the drop and keep running; the message names the field and the problem."""

from __future__ import annotations


class WireError(ValueError):
    """A received multipart message cannot be decoded."""


class UnknownSchema(WireError):
    """The header names a schema this receiver does not know."""


class UnsupportedVersion(WireError):
    """The header carries a schema version other than this receiver's."""


class MalformedMessage(WireError):
    """Frames, header, fields or array buffers do not match the schema."""


class MessageTooLarge(WireError):
    """The frames add up to more than the receiver's ``max_bytes``."""
