import sys

from gpnerf_core.cli import main

sys.exit(main())
