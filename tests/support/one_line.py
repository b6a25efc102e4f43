"""The project's rule for bad input, as the tests check it: one line that names the problem."""

from __future__ import annotations


def assert_one_line(error: BaseException, *names: str) -> None:
    """`error`'s message is a single line and contains every one of `names`."""
    message = str(error)
    assert "\n" not in message, message
    for name in names:
        assert name in message, f"{name!r} not in: {message}"
