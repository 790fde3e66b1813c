"""The one error type of the protocol package."""


class ProtocolError(ValueError):
    """A message or payload is invalid; the message says what was wrong and where.

    ``decode`` raises nothing else for any bytes, and message constructors raise it for any
    invalid field, so a site can never build or accept an invalid message.
    """
