import sys

from ballbeam.entry import main

sys.exit(main())
