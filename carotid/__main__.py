"""``python -m carotid`` runs the command line."""

import sys

from carotid.cli import main

sys.exit(main())
