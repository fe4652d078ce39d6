"""What the entry points do with bad input: print the one-sentence error, exit 2, no traceback.

Our boundaries raise FileNotFoundError/ValueError/... with a sentence naming the file or value; a user should
see that sentence, not a stack. Set RUSLAM_DEBUG=1 to get the full traceback instead.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

USER_ERRORS = (FileNotFoundError, NotADirectoryError, ValueError, KeyError, TypeError)


def run_cli(fn: Callable, *args):
    try:
        return fn(*args)
    except USER_ERRORS as err:
        if os.environ.get("RUSLAM_DEBUG"):
            raise
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
