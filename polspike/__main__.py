"""``python -m polspike``: the console script (what ``torchrun ... -m polspike train`` starts on each rank)."""

import sys

from polspike.cli import app

if __name__ == "__main__":
    sys.argv[0] = "polspike"
    app()
