"""``python -m ballbeam_emulator CONFIG``: the same as ``ballbeam emulator CONFIG``."""

import sys

from ballbeam.cli import main

sys.exit(main(["emulator", *sys.argv[1:]]))
