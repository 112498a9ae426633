"""``python -m ballbeam_emulator [CONFIG] [--set KEY=VALUE]``: the plant emulator process."""

import sys

from ballbeam_emulator.main import main

sys.exit(main())
