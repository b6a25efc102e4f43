"""Exceptions whose messages are meant for the person on the other end of the wire."""


class InvalidRequest(ValueError):
    """A request that cannot be served as sent. Its message names the problem and is returned to the client."""
