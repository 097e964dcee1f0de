import sys

from satsweep.cli import console_main

sys.exit(console_main())
