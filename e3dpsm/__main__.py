import sys

from e3dpsm.cli import main

sys.exit(main())
