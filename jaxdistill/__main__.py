"""`python -m jaxdistill COMMAND ...`: the `jaxdistill` command (jaxdistill/cli.py)."""

import sys

from jaxdistill.cli import main

sys.exit(main())
