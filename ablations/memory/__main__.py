"""``python -m ablations.memory --point JSON --result PATH``: one sweep point in this (fresh) process."""

import sys

from ablations.memory.worker import main

if __name__ == "__main__":
    sys.exit(main())
