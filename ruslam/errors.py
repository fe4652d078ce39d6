"""The project's input-error types: what a user got wrong, as one sentence naming the file or value.

`run_cli` prints these as ``error: <sentence>`` and exits 2; every other exception is a bug and keeps its
traceback. `InputError` subclasses ValueError (and `MissingInput` FileNotFoundError), so callers that caught the
built-in types before still do.
"""

from __future__ import annotations


class InputError(ValueError):
    """A config value, file, folder or array given to ruslam is not what it must be."""


class MissingInput(InputError, FileNotFoundError):
    """A file or folder the user named (or that a default expects) does not exist."""


class MissingWeights(MissingInput):
    """An extractor's or teacher's weights file is absent; an evaluation may skip that extractor with a note."""
