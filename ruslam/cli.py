"""The one error boundary of the entry points: bad input prints one sentence and exits 2, no traceback.

Boundaries raise `ruslam.errors.InputError` with a sentence naming the file or value; Hydra wraps errors raised
while instantiating a `_target_` in an InstantiationException, which is unwrapped to its cause here, and an unset
``???`` value is named by its key. Any other exception (KeyError, TypeError, ...) is a bug: it keeps its traceback.
Set RUSLAM_DEBUG=1 to get the traceback of an input error too.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

from omegaconf.errors import MissingMandatoryValue

from ruslam.errors import InputError

EXIT_BAD_INPUT = 2


def missing_value_message(key: str) -> str:
    """The sentence for an unset ``???`` config value, e.g. 'dataset.root is not set: pass dataset.root=...'."""
    leaf = key.rsplit(".", 1)[-1]
    example = {"root": "/path/to/folder", "path": "/path/to/file"}.get(leaf, "/path/to/weights" if "weights" in leaf
                                                                         else "<value>")
    return f"{key} is not set: pass {key}={example}"


def input_error_of(err: BaseException) -> InputError | None:
    """The user's mistake behind `err` (itself, or the cause Hydra wrapped), else None."""
    seen = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        if isinstance(err, InputError):
            return err
        if isinstance(err, MissingMandatoryValue):
            return InputError(missing_value_message(err.full_key or str(err.key)))
        if type(err).__name__ != "InstantiationException":
            return None
        err = err.__cause__ or err.__context__
    return None


def run_cli(fn: Callable, *args):
    try:
        return fn(*args)
    except Exception as err:
        user = input_error_of(err)
        if user is None or os.environ.get("RUSLAM_DEBUG"):
            raise
        print(f"error: {user}", file=sys.stderr)
        sys.exit(EXIT_BAD_INPUT)
