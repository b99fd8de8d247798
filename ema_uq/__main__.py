"""``python -m ema_uq`` runs the ``ema-uq`` command line."""
import sys

from .cli import main

sys.exit(main())
