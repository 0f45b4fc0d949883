"""``python -m rotavg_ros`` runs the ``rotavg`` command line."""

import sys

from rotavg_ros.cli import main

sys.exit(main())
