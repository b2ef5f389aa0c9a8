"""`python -m fmubuilder.cli`: the same as the `fmubuilder` command."""
import sys

from . import main

sys.exit(main())
