"""``python -m slam``: the ``slam`` command (:mod:`slam.app.cli`)."""
import sys

from slam.app.cli import main

sys.exit(main())
