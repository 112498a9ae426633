"""``python -m ballbeam_emulator [CONFIG] [--set KEY=VALUE]``: the plant emulator process."""

import sys

from ballbeam.entry import limit_blas_threads

limit_blas_threads()  # before numpy: the emulator's imports load it

from ballbeam_emulator.main import main  # noqa: E402

sys.exit(main())
