"""``python -m bags.cli.train ...`` (and ``torchrun ... -m bags.cli.train ...``) runs ``bev-train``."""

import sys

from .main import main

if __name__ == "__main__":  # not in a spawned process re-importing this module as __mp_main__
    sys.exit(main())
