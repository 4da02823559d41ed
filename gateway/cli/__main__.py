"""``python -m gateway.cli``: the `hookwatch` console command."""
import sys

from . import main

sys.exit(main())
