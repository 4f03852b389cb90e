import sys

from mpipack.cli import main

sys.exit(main())
