import sys

from vislam.cli import main

sys.exit(main())
