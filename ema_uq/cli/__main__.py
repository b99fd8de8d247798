"""``python -m ema_uq.cli`` runs the ``ema-uq`` command line, as ``python -m ema_uq`` does."""
import sys

from .app import main

sys.exit(main())
