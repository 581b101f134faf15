import sys

from fedmap.cli import main

sys.exit(main())
