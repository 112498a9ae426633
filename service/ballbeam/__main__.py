import sys

from ballbeam.cli import main

sys.exit(main())
