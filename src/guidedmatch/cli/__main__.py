"""``python -m guidedmatch.cli``: the console script ``guidedmatch``."""
import sys

from . import main

if __name__ == "__main__":
    sys.exit(main())
