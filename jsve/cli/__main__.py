import sys

from jsve.cli import main

sys.exit(main())
