"""``python -m canrls`` runs the command line."""

import sys

from canrls.cli.main import main

sys.exit(main())
