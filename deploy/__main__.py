"""`python -m smana.deploy` is the `smana` command."""

import sys

from smana.deploy.cli import main

if __name__ == "__main__":
    sys.exit(main())
