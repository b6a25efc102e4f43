"""Exceptions whose messages are meant for the person on the other end of the wire or the command line, and the one
way a library's complaint about a user's file becomes one of them (`reading`, `load_json`)."""

from __future__ import annotations

import contextlib
import json
import os
import pickle
import zipfile
import zlib
from collections.abc import Iterator
from typing import Any


class InvalidRequest(ValueError):
    """A request that cannot be served as sent. Its message names the problem and is returned to the client."""


class BadFile(ValueError):
    """A user's file that cannot be read as what it should be. Its message is one line naming the file and what is
    wrong; a ValueError, so that every command's one-line report of bad input reports it."""


# What a library raises for bytes that are not its format, by the name of the class or of one of its bases, so that
# this module imports none of the libraries (the viewers import no JAX, the server no pyarrow): safetensors' header and
# buffer checks, every pyarrow error (ArrowInvalid for a parquet footer, ArrowIOError for a cut file), every FFmpeg
# error of PyAV (InvalidDataError for a file that is not a video), protobuf's parse error.
_FORMAT_ERROR_NAMES = frozenset({"SafetensorError", "ArrowException", "FFmpegError", "DecodeError"})
# The standard library's and NumPy's: JSON and text decoding (ValueError, UnicodeError), npz members cut short or
# damaged (zipfile, zlib, EOFError), `.npy` headers NumPy cannot parse (ValueError), pickles that are not.
_FORMAT_ERRORS = (ValueError, EOFError, zipfile.BadZipFile, zlib.error, pickle.UnpicklingError)


def one_line(text: object) -> str:
    """`text` with every run of whitespace, line breaks included, as one space."""
    return " ".join(str(text).split())


def _is_format_error(error: BaseException, also: tuple[type[BaseException], ...]) -> bool:
    if type(error).__module__.startswith("openpi_cam"):
        return False  # the project's own errors already say what is wrong, and where
    named = any(c.__name__ in _FORMAT_ERROR_NAMES for c in type(error).__mro__)
    return named or isinstance(error, _FORMAT_ERRORS + also)


@contextlib.contextmanager
def reading(path: str | os.PathLike[str], kind: str, *also: type[BaseException]) -> Iterator[None]:
    """Around the library call that reads `path`: an error that says its bytes are not a `kind` ("safetensors file",
    "parquet file", ...) becomes a `BadFile` naming the file. `also`: what else the library raises for such bytes
    (SentencePiece a RuntimeError, the tokenizers library a bare Exception). Missing files and other OSErrors pass
    unchanged: their messages name the file already."""
    try:
        yield
    except Exception as e:
        if not _is_format_error(e, also):
            raise
        raise BadFile(f"{os.fspath(path)}: {unreadable(kind, e)}") from e


def unreadable(kind: str, error: BaseException) -> str:
    """What is wrong with a file whose library raised `error` reading it as a `kind`, in one line."""
    return f"not a readable {kind} ({one_line(error) or type(error).__name__})"


_JSON_TYPES = {dict: "an object", list: "an array", str: "a string", bool: "a boolean", type(None): "null"}


def _json_type(value: Any) -> str:
    return _JSON_TYPES.get(type(value), "a number")


def load_json(path: str | os.PathLike[str], expected: type = dict) -> Any:
    """A JSON file holding a value of type `expected` (dict: an object, or list): anything else is a `BadFile`
    saying what the file holds instead."""
    with reading(path, "JSON file"), open(path, encoding="utf-8") as f:
        value = json.load(f)
    if not isinstance(value, expected):
        raise BadFile(f"{os.fspath(path)}: holds {_json_type(value)}, expected {_json_type(expected())}")
    return value
